"""Memory of the API process under frame floods: ten devices each sending 64 frames of
8 MB at once.

Starts ``vloc serve`` (default settings but the worker count) on a free port, builds a
small map, opens one session per device, then every device posts its frames with
``--in-flight`` requests at a time, sending a refused frame (429/503) again after its
``Retry-After``. The API process's resident memory is sampled every 50 ms from /proc
(its worker processes are separate and not counted); its kernel-kept peak (VmHWM) is
read at the end.

The bound the server keeps: resident memory at most the idle process plus
``BOUND_FACTOR`` x ``VLOC_MAX_QUEUED_BYTES`` (a frame's bytes exist up to three times while
it is read, checked and handed on to a worker).

    python bench/bench_admission.py [--devices 10] [--frames 64] [--in-flight 8]
                                    [--out bench/results/admission.md]
"""

from __future__ import annotations

import argparse
import asyncio
import os
import platform
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path

import cv2
import httpx
import numpy as np
from _common import RESULTS, repo_on_path, write_result

repo_on_path()

from bench_service import ADMIN_KEY, start_server  # noqa: E402

from tests.app.imagery import map_and_queries  # noqa: E402

ADMIN = {"Authorization": f"Bearer {ADMIN_KEY}"}
BOUND_FACTOR = 3
MIB = 2**20


def rss_mib(pid: int, field: str = "VmRSS") -> float:
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024
    raise KeyError(field)


def big_jpeg(target: int, seed: int) -> bytes:
    """A valid JPEG of about ``target`` bytes (noise compresses badly)."""
    rng = np.random.default_rng(seed)
    side = int((target / 1.18) ** 0.5)
    image = rng.integers(0, 256, (side * 3 // 4, side * 4 // 3, 3), dtype=np.uint8)
    return cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes()


async def device(http: httpx.AsyncClient, sid: str, token: str, frame: bytes, frames: int,
                 in_flight: int, codes: Counter) -> None:
    headers = {"Authorization": f"Bearer {token}", "Content-Type": "image/jpeg"}
    todo = list(range(frames))
    gate = asyncio.Semaphore(in_flight)

    async def send() -> None:
        async with gate:
            while True:
                r = await http.post(f"/v1/sessions/{sid}/frames", content=frame,
                                    headers=headers)
                codes[r.status_code] += 1
                if r.status_code not in (429, 503):
                    return
                await asyncio.sleep(float(r.headers.get("retry-after", "1")))

    await asyncio.gather(*(send() for _ in todo))
    for _ in range(6000):  # until every frame is answered
        read = (await http.get(f"/v1/sessions/{sid}", headers=headers)).json()
        if read["frames_processed"] + read["frames_failed"] >= frames:
            return
        await asyncio.sleep(0.1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--devices", type=int, default=10)
    ap.add_argument("--frames", type=int, default=64)
    ap.add_argument("--in-flight", type=int, default=8)
    ap.add_argument("--frame-mb", type=float, default=8.0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", type=Path, default=RESULTS / "admission.md")
    args = ap.parse_args()

    frame = big_jpeg(int(args.frame_mb * 1e6), 1)
    with tempfile.TemporaryDirectory() as tmp:
        proc, base = start_server(Path(tmp) / "data", args.workers, max_pending_frames=None)
        try:
            samples: list[float] = []
            stop = threading.Event()

            def sample() -> None:
                while not stop.is_set():
                    samples.append(rss_mib(proc.pid))
                    time.sleep(0.05)

            async def run() -> tuple[float, Counter, float]:
                maps, _ = map_and_queries(6)
                async with httpx.AsyncClient(base_url=base, headers=ADMIN,
                                             timeout=600) as http:
                    map_id = (await http.post("/v1/maps", json={"name": "flood"})).json()["id"]
                    files = [("files", (s.name, s.jpeg, "image/jpeg")) for s in maps]
                    await http.post(f"/v1/maps/{map_id}/images", files=files)
                    job = (await http.post(f"/v1/maps/{map_id}/build")).json()["job_id"]
                    while (await http.get(f"/v1/jobs/{job}")).json()["status"] != "done":
                        await asyncio.sleep(0.2)
                    sessions = [(await http.post("/v1/sessions", json={
                        "map_id": map_id, "params": {"n_particles": 60}})).json()
                        for _ in range(args.devices)]
                    idle = rss_mib(proc.pid)
                    codes: Counter = Counter()
                    threading.Thread(target=sample, daemon=True).start()
                    t0 = time.perf_counter()
                    await asyncio.gather(*(device(http, s["id"], s["token"], frame, args.frames,
                                                  args.in_flight, codes) for s in sessions))
                    return idle, codes, time.perf_counter() - t0

            idle, codes, took = asyncio.run(run())
            stop.set()
            peak = rss_mib(proc.pid, "VmHWM")
        finally:
            proc.terminate()
            proc.wait(60)

    from vloc.app.config import Settings

    budget = Settings().max_queued_bytes / MIB
    bound = idle + BOUND_FACTOR * budget
    lines = [
        "# API memory under a frame flood",
        "",
        f"`python bench/bench_admission.py --devices {args.devices} --frames {args.frames} "
        f"--in-flight {args.in_flight} --workers {args.workers}` on {platform.machine()}, "
        f"{os.cpu_count()} CPUs, SQLite, default limits (VLOC_MAX_QUEUED_BYTES "
        f"{budget:.0f} MiB).",
        "",
        f"{args.devices} devices each post {args.frames} frames of {len(frame) / 1e6:.1f} MB "
        f"({args.in_flight} requests in flight per device; a refused frame is sent again "
        "after its Retry-After).",
        "",
        "| measure | value |",
        "|---|---|",
        f"| API resident memory, idle with the sessions open | {idle:.0f} MiB |",
        f"| API resident memory during the flood, median of samples | "
        f"{float(np.median(samples)):.0f} MiB |",
        f"| API resident memory, peak (VmHWM) | {peak:.0f} MiB |",
        f"| documented bound: idle + {BOUND_FACTOR} x VLOC_MAX_QUEUED_BYTES | {bound:.0f} MiB |",
        f"| answers | {', '.join(f'{k}: {v}' for k, v in sorted(codes.items()))} |",
        f"| frames answered | {args.devices * args.frames} in {took:.0f} s |",
        "",
        "Worker processes hold their own frames (one at a time each) and are not counted.",
        "",
    ]
    write_result(args.out, "\n".join(lines))
    if peak > bound:
        raise SystemExit(f"peak {peak:.0f} MiB is over the bound {bound:.0f} MiB")


if __name__ == "__main__":
    main()
