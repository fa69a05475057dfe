"""Where a session's filter lives on Ray: one actor per session against shard actors.

Both placements run the engine's own actor (:class:`workers.engine.ray_engine.Shard`) on a
local Ray cluster this script starts, over the map of seneca-uav pass 1 in the object store
(:class:`~workers.engine.ray_engine.MapStore`), with hybrid sessions (``default``) stepping
pass-2 frames:

- ``shards``: W shard actors (W = the machine's CPUs), each holding many sessions, a session
  on the shard its id hashes to (what :class:`~workers.engine.ray_engine.RayEngine` does);
- ``per-session``: one actor per session, named after it. Each reserves an equal share of
  the CPUs (W / N): with a whole CPU each, Ray would start only W of them.

For N = 1, 10, 50 sessions: the time to start the actors and open the sessions, the memory
of the actor processes (RSS, and PSS from ``/proc/<pid>/smaps_rollup``, which shares the
map's pages among the processes that map them), and, with every session sending its frames
one at a time (next frame once the last is answered), the frames/s and the latency of a
frame (reserve its seq, step it) p50/p99. The two placements alternate in every round; each
figure is the median over the rounds.

    python bench/bench_actor_placement.py [--sessions 1,10,50] [--frames 20,6,3]
                                          [--rounds 3] [--out bench/results/actor_placement.md]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import tempfile
import threading
import time
import uuid
from pathlib import Path

import numpy as np
import ray
from _common import DATASETS, RESULTS, repo_on_path, write_result

repo_on_path()

from vloc.workers.core.evaluation.datasets import load_dataset, load_frames, split  # noqa: E402
from vloc.workers.core.evaluation.experiment import build_map  # noqa: E402
from vloc.workers.engine import SessionSpec  # noqa: E402
from vloc.workers.engine.ray_actors import MAP_STORE, MapStore, Shard  # noqa: E402
from vloc.workers.engine.ray_engine import shard_of  # noqa: E402

PLACEMENTS = ("shards", "per-session")


def memory_kb(pid: int) -> tuple[int, int]:
    """(RSS, PSS) of a process in kB."""
    fields = {}
    with open(f"/proc/{pid}/smaps_rollup") as f:
        for line in f:
            parts = line.split()
            if len(parts) >= 2 and parts[1].isdigit():
                fields[parts[0].rstrip(":")] = int(parts[1])
    return fields.get("Rss", 0), fields.get("Pss", 0)


def start_actors(placement: str, n_sessions: int, n_cpus: int, namespace: str) -> list:
    cls = ray.remote(Shard)
    if placement == "shards":
        count, cpus = n_cpus, 1.0
    else:
        count, cpus = n_sessions, min(1.0, n_cpus / n_sessions)
    return [cls.options(name=f"bench-{placement}-{i}", namespace=namespace, num_cpus=cpus,
                        max_concurrency=1000)
            .remote(i, max_pixels=50_000_000, checkpoint_every=10**9, namespace=namespace)
            for i in range(count)]


def run_level(placement: str, n_sessions: int, n_frames: int, frames: list[bytes],
              stamps: list[float | None], map_folder: str, n_cpus: int,
              namespace: str) -> dict:
    t0 = time.perf_counter()
    actors = start_actors(placement, n_sessions, n_cpus, namespace)
    pids = [pid for pid, _ in ray.get([a.ping.remote() for a in actors])]
    started_s = time.perf_counter() - t0
    sids = [f"s{uuid.uuid4().hex[:12]}" for _ in range(n_sessions)]

    def actor_of(i: int):
        return actors[shard_of(sids[i], len(actors))] if placement == "shards" else actors[i]

    t1 = time.perf_counter()
    opened = ray.get([actor_of(i).open.remote(
        SessionSpec(session_id=sid, map_id="seneca", revision=1, map_folder=map_folder,
                    mode="hybrid", params={"config": "default"}, seed=i), None, None)
        for i, sid in enumerate(sids)])
    open_s = time.perf_counter() - t1
    if any(o[0] == "error" for o in opened):
        raise RuntimeError(f"a session did not open: {opened}")
    latencies: list[float] = []
    lock = threading.Lock()

    def drive(i: int) -> None:
        actor, sid, mine = actor_of(i), sids[i], []
        for k in range(n_frames):
            j = (i * 7 + k) % len(frames)  # sessions start at different frames
            t = time.perf_counter()
            _, seq = ray.get(actor.reserve.remote(sid, None))
            done = ray.get(actor.frame.remote(sid, seq, frames[j], stamps[j], None))
            if not hasattr(done, "estimate"):
                raise RuntimeError(f"frame failed: {done}")
            mine.append((time.perf_counter() - t) * 1e3)
        with lock:
            latencies.extend(mine)

    threads = [threading.Thread(target=drive, args=(i,)) for i in range(n_sessions)]
    t2 = time.perf_counter()
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    wall = time.perf_counter() - t2
    mem = [memory_kb(pid) for pid in pids]
    for a in actors:
        ray.kill(a)
    return {"placement": placement, "sessions": n_sessions, "actors": len(actors),
            "frames": len(latencies), "start_s": started_s, "open_s": open_s,
            "fps": len(latencies) / wall, "p50": float(np.percentile(latencies, 50)),
            "p99": float(np.percentile(latencies, 99)),
            "rss_mb": sum(r for r, _ in mem) / 1024, "pss_mb": sum(p for _, p in mem) / 1024}


def markdown(rows: list[dict], args, n_cpus: int) -> str:
    keys = ("start_s", "open_s", "fps", "p50", "p99", "rss_mb", "pss_mb")
    merged = {}
    for r in rows:
        merged.setdefault((r["placement"], r["sessions"]), []).append(r)
    lines = ["# Sessions on Ray: one actor per session against shard actors", "",
             f"`python bench/bench_actor_placement.py --sessions {args.sessions} "
             f"--frames {args.frames} --rounds {args.rounds}`", "",
             f"Machine: {platform.machine()}, {n_cpus} logical CPUs shared with other work "
             f"(1-minute load average {os.getloadavg()[0]:.1f} at the end); Python "
             f"{platform.python_version()}, Ray {ray.__version__}. Map: seneca-uav pass 1 in "
             "the object store; frames: pass 2 (1024x768 JPEG), hybrid, `default`. Each figure "
             "is the median over the rounds.", "",
             "| placement | sessions | actors | frames | start actors (s) | open sessions (s) "
             "| frames/s | latency p50 (ms) | latency p99 (ms) | actors' RSS (MB) "
             "| actors' PSS (MB) |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for (placement, n), rs in merged.items():
        med = {k: statistics.median(r[k] for r in rs) for k in keys}
        lines.append(f"| {placement} | {n} | {rs[0]['actors']} | {rs[0]['frames']} | "
                     f"{med['start_s']:.2f} | {med['open_s']:.2f} | {med['fps']:.1f} | "
                     f"{med['p50']:.1f} | {med['p99']:.1f} | {med['rss_mb']:.0f} | "
                     f"{med['pss_mb']:.0f} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--dataset", type=Path, default=DATASETS / "seneca-uav")
    p.add_argument("--sessions", default="1,10,50")
    p.add_argument("--frames", default="20,6,3", help="frames per session at each level")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--out", type=Path, default=RESULTS / "actor_placement.md")
    args = p.parse_args()
    levels = [int(x) for x in args.sessions.split(",")]
    counts = [int(x) for x in args.frames.split(",")]
    if len(levels) != len(counts):
        raise SystemExit("--frames needs one count per --sessions level")
    ds = load_dataset(args.dataset)
    map_images, query_images = split(ds, "pass", map_pass=1, query_pass=2)
    frames = [im.path.read_bytes() for im in query_images]
    stamps = [im.captured_at.timestamp() if im.captured_at else None for im in query_images]
    folder = Path(tempfile.mkdtemp(prefix="vloc-bench-placement-")) / "map"
    build_map(map_images, load_frames(map_images), map_id="seneca").save(folder)
    n_cpus = os.cpu_count() or 1
    namespace = f"bench-placement-{uuid.uuid4().hex[:8]}"
    ray.init(num_cpus=n_cpus, namespace=namespace, include_dashboard=False,
             log_to_driver=False)
    store = ray.remote(MapStore).options(name=MAP_STORE, num_cpus=0).remote()
    ray.get(store.stats.remote())  # up, and kept: an actor without a handle is stopped
    rows = []
    try:
        for r in range(args.rounds):
            order = PLACEMENTS if r % 2 == 0 else PLACEMENTS[::-1]
            for n, k in zip(levels, counts, strict=True):
                for placement in order:
                    row = run_level(placement, n, k, frames, stamps, str(folder), n_cpus,
                                    namespace)
                    rows.append(row)
                    print({k: round(v, 2) if isinstance(v, float) else v
                           for k, v in row.items()}, flush=True)
    finally:
        ray.shutdown()
    text = markdown(rows, args, n_cpus)
    write_result(args.out, text)


if __name__ == "__main__":
    main()
