"""A map that grows: rebuilding after images are added, against building it whole.

Starts ``vloc serve`` (SQLite, ``--workers`` engine processes) and builds two maps of
seneca-uav pass 1 over HTTP: one of the first images, then the last ``--added`` uploaded
and the map rebuilt (the rebuild takes up the tie points and matched pairs the map keeps
from its first build), and one of every image built at once. Reports each build's wall time
by stage (the job's ``stage``, polled) and checks that the rebuilt map's cameras are the
whole build's, bit for bit.

    python bench/bench_rebuild.py [--dataset PATH] [--added 10] [--workers 2]
                                  [--out bench/results/rebuild.md]
"""

from __future__ import annotations

import argparse
import os
import platform
import signal
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

from bench_large_map import build as build_job  # noqa: E402
from bench_service import ADMIN_KEY, start_server  # noqa: E402

from vloc.workers.core.evaluation.datasets import load_dataset, split  # noqa: E402
from vloc.workers.core.mapdata import MapData  # noqa: E402

ADMIN = {"Authorization": f"Bearer {ADMIN_KEY}"}


def upload(http: httpx.Client, map_id: str, images) -> None:
    files = [("files", (im.name, im.path.read_bytes(), "image/jpeg")) for im in images]
    http.post(f"/v1/maps/{map_id}/images", files=files, headers=ADMIN).raise_for_status()


def build(http: httpx.Client, map_id: str) -> tuple[float, dict[str, float]]:
    """Build the map; its wall time and the seconds spent in each of the job's stages."""
    t0 = time.perf_counter()
    job, stages = build_job(http, map_id, headers=ADMIN)
    if job["status"] != "done":
        raise SystemExit(f"build failed: {job['error']}")
    return time.perf_counter() - t0, stages


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--dataset", type=Path,
                   default=REPO.parent / "shared" / "datasets" / "seneca-uav")
    p.add_argument("--added", type=int, default=10)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "rebuild.md")
    args = p.parse_args()
    images, _ = split(load_dataset(args.dataset), "pass", map_pass=1, query_pass=2)
    first, added = images[:-args.added], images[-args.added:]
    tmp = Path(tempfile.mkdtemp(prefix="vloc-bench-"))
    proc, base = start_server(tmp / "data", args.workers)
    try:
        with httpx.Client(base_url=base, timeout=600) as http:
            grown = http.post("/v1/maps", json={"name": "grown"}, headers=ADMIN).json()["id"]
            whole = http.post("/v1/maps", json={"name": "whole"}, headers=ADMIN).json()["id"]
            upload(http, grown, first)
            timed = {"first": build(http, grown)}
            upload(http, grown, added)
            timed["rebuild"] = build(http, grown)
            upload(http, whole, images)
            timed["whole"] = build(http, whole)
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(60)
    a = MapData.load(tmp / "data" / "maps" / grown / "rev-000002")
    b = MapData.load(tmp / "data" / "maps" / whole / "rev-000001")
    same = (a.geometry is None) == (b.geometry is None) and (
        a.geometry is None or np.array_equal(a.geometry.centres, b.geometry.centres,
                                             equal_nan=True))
    stages = sorted({s for _, st in timed.values() for s in st})
    label = {"first": f"first build, {len(first)} images",
             "rebuild": f"rebuild after {len(added)} added ({len(images)} images)",
             "whole": f"all {len(images)} images built at once"}
    rows = [f"| {label[k]} | {wall:.1f} | " + " | ".join(f"{st.get(s, 0.0):.1f}" for s in stages)
            + " |" for k, (wall, st) in timed.items()]
    text = "\n".join([
        "# Rebuilding a map that grew", "",
        f"`python bench/bench_rebuild.py --added {args.added} --workers {args.workers}`", "",
        f"Machine: {platform.machine()}, {os.cpu_count()} logical CPUs; {args.workers} "
        f"worker process(es); SQLite; seneca-uav pass 1. Wall seconds at the client, and by "
        "the build job's stage (polled every 0.5 s).", "",
        "| build | wall s | " + " | ".join(stages) + " |",
        "|---|---|" + "---|" * len(stages), *rows, "",
        f"Rebuild / whole build: {timed['rebuild'][0] / timed['whole'][0]:.2f}. The rebuilt "
        f"map's cameras are the whole build's, bit for bit: {'yes' if same else 'NO'}.", ""])
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(text)
    if not same:
        raise SystemExit("the rebuilt map differs from the whole build")


if __name__ == "__main__":
    main()
