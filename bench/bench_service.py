"""Service benchmark: frame-to-pose latency and throughput through the real server.

Starts ``vloc serve`` on a free port, builds the map of seneca-uav pass 1 over HTTP, then for
each concurrency level opens that many hybrid sessions; every session streams pass-2 frames
(the raw 1024x768 JPEGs) one at a time: POST the frame, wait for its pose on the session's
WebSocket, send the next. Latency is measured at the client, from the start of the POST to
the arrival of the pose message.

Reported per level: frames per second over the whole level, latency p50/p99, the core's step
time and the worker's decode time (both from the pose messages), and the time the service
adds on top of them (latency - step - decode): HTTP in, header checks, queueing, the result
pipe, the database write, the WebSocket out.

    python bench/bench_service.py [--dataset PATH] [--sessions 1,10,100] [--workers N]
                                  [--frames 97,30,6] [--out bench/results/service.md]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import platform
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np
from _common import DATASETS, RESULTS, ROOT, repo_on_path, write_result
from websockets.asyncio.client import connect

repo_on_path()

from vloc.workers.core.evaluation.datasets import load_dataset, split  # noqa: E402

ADMIN_KEY = "bench-admin-key-0123456789abcdef"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_ready(proc: subprocess.Popen, base: str, tries: int = 600) -> bool:
    """Whether the server at ``base`` answers ``/readyz`` within ``tries`` polls 0.2 s apart;
    False as soon as its process exits."""
    for _ in range(tries):
        if proc.poll() is not None:
            return False
        try:
            if httpx.get(base + "/readyz", timeout=1).status_code == 200:
                return True
        except httpx.TransportError:
            pass
        time.sleep(0.2)
    return False


def start_server(data_dir: Path, workers: int, *, max_pending_frames: int | None = 1000,
                 ) -> tuple[subprocess.Popen, str]:
    """``vloc serve`` on a free port, on SQLite in ``data_dir``, its log beside it; once
    ready, the process and the base URL. ``max_pending_frames=None`` keeps the server's
    own limit."""
    port = free_port()
    env = {**os.environ, "VLOC_DATA_DIR": str(data_dir), "VLOC_WORKERS": str(workers),
           "VLOC_ADMIN_KEY": ADMIN_KEY, "VLOC_LOG_LEVEL": "WARNING"}
    if max_pending_frames is not None:
        env["VLOC_MAX_PENDING_FRAMES"] = str(max_pending_frames)
    env.pop("VLOC_DATABASE_URL", None)
    proc = subprocess.Popen([sys.executable, "-m", "vloc.clients.cli", "serve", "--port", str(port)],
                            cwd=ROOT, env=env, stdout=subprocess.DEVNULL,
                            stderr=(data_dir.parent / "server.log").open("wb"))
    base = f"http://127.0.0.1:{port}"
    if wait_ready(proc, base):
        return proc, base
    proc.kill()
    raise SystemExit("the server did not start; see " + str(data_dir.parent / "server.log"))


async def build_map(http: httpx.AsyncClient, images) -> str:
    map_id = (await http.post("/v1/maps", json={"name": "seneca pass 1"})).json()["id"]
    files = [("files", (im.name, im.path.read_bytes(), "image/jpeg")) for im in images]
    r = await http.post(f"/v1/maps/{map_id}/images", files=files)
    r.raise_for_status()
    job_id = (await http.post(f"/v1/maps/{map_id}/build")).json()["job_id"]
    while (job := (await http.get(f"/v1/jobs/{job_id}")).json())["status"] not in (
            "done", "failed"):
        await asyncio.sleep(0.5)
    if job["status"] != "done":
        raise SystemExit(f"build failed: {job['error']}")
    return map_id


async def one_session(http, ws_base, map_id, seed, frames, stamps, out: list) -> None:
    r = await http.post("/v1/sessions", json={"map_id": map_id, "mode": "hybrid",
                                              "params": {"config": "default"}, "seed": seed})
    r.raise_for_status()
    sid, token = r.json()["id"], r.json()["token"]
    headers = {"Authorization": f"Bearer {token}", "Content-Type": "image/jpeg"}
    async with connect(f"{ws_base}/v1/sessions/{sid}/stream",
                       additional_headers={"Authorization": f"Bearer {token}"},
                       max_size=2**24) as ws:
        json.loads(await ws.recv())  # hello
        for data, stamp in zip(frames, stamps, strict=True):
            t0 = time.perf_counter()
            r = await http.post(f"/v1/sessions/{sid}/frames", content=data, headers=headers,
                                params={"captured_at": stamp} if stamp else None)
            r.raise_for_status()
            msg = json.loads(await ws.recv())
            t1 = time.perf_counter()
            if msg["type"] != "pose":
                raise SystemExit(f"frame failed: {msg}")
            out.append(((t1 - t0) * 1e3, msg["processing_ms"], msg["decode_ms"],
                        msg["latency_ms"], msg["feature"]))
    await http.delete(f"/v1/sessions/{sid}")


async def level(base: str, map_id: str, n_sessions: int, frames, stamps) -> dict:
    limits = httpx.Limits(max_connections=n_sessions + 4, max_keepalive_connections=n_sessions)
    samples: list = []
    async with httpx.AsyncClient(base_url=base, timeout=600, limits=limits,
                                 headers={"Authorization": f"Bearer {ADMIN_KEY}"}) as http:
        t0 = time.perf_counter()
        await asyncio.gather(*(one_session(http, base.replace("http", "ws"), map_id, seed,
                                           frames, stamps, samples)
                               for seed in range(n_sessions)))
        wall = time.perf_counter() - t0
    a = np.array([s[:4] for s in samples])
    latency, step, decode, server = a[:, 0], a[:, 1], a[:, 2], a[:, 3]
    added = latency - step - decode
    return {"sessions": n_sessions, "frames": len(samples), "fps": len(samples) / wall,
            "latency_p50": np.percentile(latency, 50), "latency_p99": np.percentile(latency, 99),
            "step_p50": np.percentile(step, 50), "decode_p50": np.percentile(decode, 50),
            "added_p50": np.percentile(added, 50), "added_p99": np.percentile(added, 99),
            "over_step_p50": np.percentile(latency - step, 50),
            "server_latency_p50": np.percentile(server, 50),
            "sift_share": float(np.mean([s[4] == "sift" for s in samples]))}


def markdown(rows: list[dict], args, n_map: int, cpu: str) -> str:
    head = ("| sessions | frames | frames/s | latency p50 (ms) | latency p99 (ms) "
            "| step p50 (ms) | decode p50 (ms) | added p50 (ms) | added p99 (ms) "
            "| latency - step, p50 (ms) | SIFT share |\n|" + "---|" * 11)
    lines = [f"| {r['sessions']} | {r['frames']} | {r['fps']:.1f} | {r['latency_p50']:.1f} "
             f"| {r['latency_p99']:.1f} | {r['step_p50']:.1f} | {r['decode_p50']:.1f} "
             f"| {r['added_p50']:.1f} | {r['added_p99']:.1f} | {r['over_step_p50']:.1f} "
             f"| {r['sift_share']:.2f} |" for r in rows]
    return "\n".join([
        "# Service benchmark: frame to pose through the real server", "",
        f"`python bench/bench_service.py --sessions {args.sessions} --frames {args.frames} "
        f"--workers {args.workers}`", "",
        f"Machine: {cpu}, {os.cpu_count()} logical CPUs; {args.workers} worker processes; "
        f"SQLite (embedded default). Map: seneca-uav pass 1 ({n_map} images); frames: pass 2 "
        "(1024x768 JPEG), hybrid mode, default config, one frame in flight per session.", "",
        head, *lines, "",
        "- *latency*: client-side, start of `POST /frames` to the pose on the WebSocket.",
        "- *step*: the core's own step time (`processing_ms`); *decode*: JPEG decoding and "
        "resizing in the worker (`decode_ms`).",
        "- *added* = latency - step - decode: what the service adds (HTTP, checks, queues, "
        "pipes, database write, WebSocket). With more sessions than workers it includes "
        "waiting for a busy worker.", ""])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--dataset", type=Path, default=DATASETS / "seneca-uav")
    p.add_argument("--sessions", default="1,10,100")
    p.add_argument("--frames", default="97,30,6",
                   help="frames per session at each level (from the start of pass 2)")
    p.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    p.add_argument("--out", type=Path, default=RESULTS / "service.md")
    args = p.parse_args()
    levels = [int(x) for x in args.sessions.split(",")]
    counts = [int(x) for x in args.frames.split(",")]
    if len(counts) != len(levels):
        raise SystemExit("--frames needs one count per --sessions level")
    ds = load_dataset(args.dataset)
    map_images, query_images = split(ds, "pass", map_pass=1, query_pass=2)
    all_frames = [im.path.read_bytes() for im in query_images]
    all_stamps = [repr(im.captured_at.timestamp()) if im.captured_at else None
                  for im in query_images]
    tmp = Path(tempfile.mkdtemp(prefix="vloc-bench-"))
    print(f"server data and log in {tmp}", flush=True)
    proc, base = start_server(tmp / "data", args.workers)
    try:
        async def run() -> list[dict]:
            async with httpx.AsyncClient(base_url=base, timeout=600, headers={
                    "Authorization": f"Bearer {ADMIN_KEY}"}) as http:
                map_id = await build_map(http, map_images)
            rows = []
            for n, k in zip(levels, counts, strict=True):
                k = min(k, len(all_frames))
                rows.append(await level(base, map_id, n, all_frames[:k], all_stamps[:k]))
                print(json.dumps({key: round(v, 2) if isinstance(v, float) else v
                                  for key, v in rows[-1].items()}), flush=True)
            return rows

        rows = asyncio.run(run())
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(60)
    cpu = platform.processor() or platform.machine()
    text = markdown(rows, args, len(map_images), cpu)
    write_result(args.out, text)


if __name__ == "__main__":
    main()
