"""Scale-out benchmark: the local pool against the Ray engine, side by side in one run.

Every configuration is the real server (``vloc serve``) on PostgreSQL and Redis, serving the
map of seneca-uav pass 1 (built once, by the first configuration, and shared through the
database and the data directory); every session streams pass-2 frames, one in flight at a
time (POST, wait for the pose on the session's WebSocket, next), as in
``bench/bench_service.py``. Configurations:

- ``local``: the local engine with W worker processes (W = 1, 2);
- ``ray``: the Ray engine with W shard actors on a Ray cluster this script starts on the
  machine (``ray start --head``, W CPUs for the shards);
- ``ray x2 API``: two API processes (``vloc serve --processes 2``) on the same Ray shards,
  sessions spread over them by the kernel (one listening socket).

For each: frames/s over the level, client latency p50/p99, step and decode p50 (from the
pose messages), and what the service adds (latency - step - decode).

    python bench/bench_scale.py [--dataset PATH] [--sessions 1,10,50] [--frames 40,8,3]
                                [--workers 1,2] [--out bench/results/scale.md]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import platform
import signal
import subprocess
import sys
import tempfile
import uuid
from pathlib import Path

import httpx
from _common import DATASETS, RESULTS, ROOT, repo_on_path, write_result

repo_on_path()

from bench_service import ADMIN_KEY, build_map, free_port, level, wait_ready  # noqa: E402

from vloc.workers.core.evaluation.datasets import load_dataset, split  # noqa: E402

POSTGRES = os.environ.get("VLOC_TEST_POSTGRES_URL",
                          "postgresql+psycopg://postgres@127.0.0.1:5432/test")
REDIS = os.environ.get("VLOC_TEST_REDIS_URL", "redis://127.0.0.1:6379/0")


def start_ray(log: Path, cpus: int) -> tuple[subprocess.Popen, str]:
    port = free_port()
    env = {**os.environ, "RAY_AUTH_MODE": "disabled", "RAY_USAGE_STATS_ENABLED": "0"}
    head = subprocess.Popen(
        [str(Path(sys.executable).with_name("ray")), "start", "--head", "--block",
         f"--port={port}", f"--num-cpus={cpus}", "--include-dashboard=false",
         "--disable-usage-stats"], env=env, stdout=log.open("wb"), stderr=subprocess.STDOUT,
        start_new_session=True)
    return head, f"127.0.0.1:{port}"


def stop_group(proc: subprocess.Popen, timeout: float = 10) -> None:
    try:
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(10)
    except ProcessLookupError:
        pass


def start_server(tmp: Path, env: dict, processes: int) -> tuple[subprocess.Popen, str]:
    port = free_port()
    environ = {**os.environ, "VLOC_DATA_DIR": str(tmp / "data"), "VLOC_ADMIN_KEY": ADMIN_KEY,
               "VLOC_LOG_LEVEL": "WARNING", "VLOC_MAX_PENDING_FRAMES": "1000",
               "RAY_AUTH_MODE": "disabled", **env}
    log = tmp / f"server-{port}.log"
    proc = subprocess.Popen(
        [sys.executable, "-m", "vloc.clients.cli", "serve", "--port", str(port), "--processes",
         str(processes)], cwd=ROOT, env=environ, stdout=subprocess.DEVNULL,
        stderr=log.open("wb"), start_new_session=True)
    base = f"http://127.0.0.1:{port}"
    if wait_ready(proc, base, tries=900):
        return proc, base
    if proc.poll() is not None:
        raise SystemExit(f"the server exited; see {log}")
    stop_group(proc)
    raise SystemExit(f"the server did not start; see {log}")


def pg_schema() -> tuple[str, callable]:
    import psycopg
    from sqlalchemy.engine import make_url

    url = make_url(POSTGRES)
    plain = url.set(drivername="postgresql").render_as_string(hide_password=False)
    schema = f"vloc_bench_{uuid.uuid4().hex[:10]}"
    with psycopg.connect(plain, autocommit=True) as conn:
        conn.execute(f'CREATE SCHEMA "{schema}"')

    def drop() -> None:
        with psycopg.connect(plain, autocommit=True) as conn:
            conn.execute(f'DROP SCHEMA "{schema}" CASCADE')

    return url.update_query_dict({"options": f"-csearch_path={schema}"}).render_as_string(
        hide_password=False), drop


def medians(rows: list[dict]) -> list[dict]:
    """One row per (engine, workers, API processes, sessions): the median of each figure
    over the rounds, in the order the configurations first ran."""
    import numpy as np

    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["engine"], r["workers"], r["api"], r["sessions"]), []).append(r)
    out = []
    for key, runs in groups.items():
        row = dict(zip(("engine", "workers", "api", "sessions"), key, strict=True))
        row["rounds"] = len(runs)
        for k, v in runs[0].items():
            if k not in row and isinstance(v, int | float):
                row[k] = float(np.median([run[k] for run in runs]))
        out.append(row)
    return out


def markdown(rows: list[dict], args, n_map: int) -> str:
    cpu = platform.processor() or platform.machine()
    head = ("| engine | workers | API processes | sessions | frames | rounds | frames/s "
            "| latency p50 (ms) | latency p99 (ms) | step p50 (ms) | decode p50 (ms) "
            "| added p50 (ms) | added p99 (ms) |\n|" + "---|" * 13)
    lines = [f"| {r['engine']} | {r['workers']} | {r['api']} | {r['sessions']} "
             f"| {r['frames']:.0f} | {r['rounds']} | {r['fps']:.1f} | {r['latency_p50']:.1f} "
             f"| {r['latency_p99']:.1f} | {r['step_p50']:.1f} | {r['decode_p50']:.1f} "
             f"| {r['added_p50']:.1f} | {r['added_p99']:.1f} |" for r in rows]
    return "\n".join([
        "# Scale-out benchmark: local pool and Ray engine", "",
        f"`python bench/bench_scale.py --sessions {args.sessions} --frames {args.frames} "
        f"--workers {args.workers} --rounds {args.rounds}`", "",
        f"Machine: {cpu}, {os.cpu_count()} logical CPUs shared with other work; the client, "
        "the API processes, PostgreSQL, Redis and the Ray cluster all run on them. Map: "
        f"seneca-uav pass 1 ({n_map} images); frames: pass 2 (1024x768 JPEG), hybrid mode, "
        "default config, one frame in flight per session. PostgreSQL and Redis for every "
        "configuration. Ray: a head on this machine with as many CPUs as shards.", "",
        head, *lines, "",
        "- *latency*: client-side, start of `POST /frames` to the pose on the WebSocket.",
        "- *added* = latency - step - decode: what the service adds, queueing for a busy "
        "worker included.",
        "- Every figure is the median over the rounds (configurations in reversed order every "
        "other round, so that a change in the machine's other load falls on both engines).",
        ""])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--dataset", type=Path, default=DATASETS / "seneca-uav")
    p.add_argument("--sessions", default="1,10,50")
    p.add_argument("--frames", default="40,8,3",
                   help="frames per session at each level (from the start of pass 2)")
    p.add_argument("--workers", default="1,2")
    p.add_argument("--rounds", type=int, default=3,
                   help="rounds over every configuration, in reversed order every other "
                        "round; each figure is the median over the rounds")
    p.add_argument("--out", type=Path, default=RESULTS / "scale.md")
    args = p.parse_args()
    levels = [int(x) for x in args.sessions.split(",")]
    counts = [int(x) for x in args.frames.split(",")]
    workers = [int(x) for x in args.workers.split(",")]
    if len(counts) != len(levels):
        raise SystemExit("--frames needs one count per --sessions level")
    ds = load_dataset(args.dataset)
    map_images, query_images = split(ds, "pass", map_pass=1, query_pass=2)
    frames = [im.path.read_bytes() for im in query_images]
    stamps = [repr(im.captured_at.timestamp()) if im.captured_at else None
              for im in query_images]
    tmp = Path(tempfile.mkdtemp(prefix="vloc-bench-scale-"))
    print(f"data and logs in {tmp}", flush=True)
    database_url, drop = pg_schema()
    common = {"VLOC_DATABASE_URL": database_url, "VLOC_REDIS_URL": REDIS}
    configs = [("local", w, 1) for w in workers] + [("ray", w, 1) for w in workers] \
        + [("ray", max(workers), 2)]
    rows: list[dict] = []
    map_id = None
    rounds = [configs if r % 2 == 0 else configs[::-1] for r in range(args.rounds)]
    try:
        for engine, w, api in [c for order in rounds for c in order]:
            env = {**common, "VLOC_WORKERS": str(w), "VLOC_ENGINE": engine}
            head = None
            if engine == "ray":
                head, address = start_ray(tmp / f"ray-{w}-{api}.log", w)
                env.update({"VLOC_RAY_ADDRESS": address, "VLOC_RAY_SHARDS": str(w),
                            "VLOC_RAY_NAMESPACE": f"bench-{uuid.uuid4().hex[:6]}"})
            try:
                proc, base = start_server(tmp, env, api)
                try:
                    async def run(base=base) -> tuple[str, list[dict]]:
                        nonlocal map_id
                        if map_id is None:
                            async with httpx.AsyncClient(base_url=base, timeout=600, headers={
                                    "Authorization": f"Bearer {ADMIN_KEY}"}) as http:
                                map_id = await build_map(http, map_images)
                        out = []
                        for n, k in zip(levels, counts, strict=True):
                            k = min(k, len(frames))
                            out.append(await level(base, map_id, n, frames[:k], stamps[:k]))
                        return out

                    for r in asyncio.run(run()):
                        r.update(engine=engine, workers=w, api=api)
                        rows.append(r)
                        print(json.dumps({k: round(v, 2) if isinstance(v, float) else v
                                          for k, v in r.items()}), flush=True)
                finally:
                    stop_group(proc, 60)
            finally:
                if head is not None:
                    stop_group(head)
                    # ``ray start`` leaves its address for a later ray.init(): gone now.
                    current = Path("/tmp/ray/ray_current_cluster")
                    if current.is_file() and current.read_text().strip().endswith(
                            address.rsplit(":", 1)[1]):
                        current.unlink()
    finally:
        drop()
    text = markdown(medians(rows), args, len(map_images))
    write_result(args.out, text)


if __name__ == "__main__":
    main()
