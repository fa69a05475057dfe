"""Replay a built large map's reconstruction offline and print each of its acceptance checks.

The build keeps no record of why :func:`~workers.core.geometry.build_geometry` refused a
map's geometry (it returns None). This script takes the first ``--images`` images of the map
that :mod:`bench_large_map` built in ``--work`` (their files and GPS from the service's
SQLite database), extracts their tie points on ``--processes`` processes, matches the pairs
and adjusts the blocks as the build does, and prints each check beside its limit.

Usage::

    .venv/bin/python bench/large_map_geometry.py --work /work/lm12k --images 12000
"""

from __future__ import annotations

import argparse
import sqlite3
import sys
import time
from multiprocessing import Pool
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from vloc.workers.core import geometry
from vloc.workers.core.geometry.pairs import match_pairs
from vloc.workers.core.geometry.reconstruct import reconstruct_in_blocks
from vloc.workers.core.mapbuild import (
    extract_tie_points,
    initial_intrinsics,
    local_frame,
    typical_focal_px,
)


def _ties(path: str) -> tuple[np.ndarray, np.ndarray]:
    t = extract_tie_points(Path(path).read_bytes())
    return np.asarray(t.keypoints), np.asarray(t.descriptors)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--work", type=Path, required=True, help="bench_large_map's work directory")
    p.add_argument("--images", type=int, default=2000)
    p.add_argument("--processes", type=int, default=2)
    args = p.parse_args()
    db = sqlite3.connect(f"file:{args.work / 'service' / 'vloc.sqlite3'}?mode=ro", uri=True)
    rows = list(db.execute("select file_hash, lat, lon, alt from map_images order by id "
                           "limit ?", (args.images,)))
    if not rows:
        sys.exit(f"no map images in {args.work}")
    folder = next((args.work / "service" / "maps").glob("*/images"))
    files = [str(folder / f"{h}.jpg") for h, *_ in rows]
    t0 = time.perf_counter()
    with Pool(args.processes) as pool:
        ties = pool.map(_ties, files, chunksize=50)
    print(f"tie points of {len(files)} images: {time.perf_counter() - t0:.0f} s", flush=True)
    _, xy, alt = local_frame(*zip(*[r[1:] for r in rows], strict=True))
    K0 = initial_intrinsics(typical_focal_px([Path(f).read_bytes for f in files]))
    with threadpool_limits(limits=1, user_api="blas"):
        pairs = match_pairs([k for k, _ in ties], [d for _, d in ties], xy,
                            max_distance=geometry.tie_reach(xy))
        print(f"{len(pairs)} verified pairs: {time.perf_counter() - t0:.0f} s", flush=True)
        rec = reconstruct_in_blocks(pairs, xy, alt, K0)
    done = rec.reconstructed
    heights = rec.centres[done, 2]
    checks = [
        ("share reconstructed", done.mean(), ">=", geometry.MIN_RECONSTRUCTED),
        ("residual (px)", rec.residual_px, "<=", geometry.MAX_RESIDUAL_PX),
        ("GPS RMS (m)", rec.gps_rms, "<=", geometry.MAX_GPS_RMS),
        ("median height (m)", float(np.median(heights)) if len(heights) else float("nan"),
         ">=", geometry.MIN_HEIGHT),
        ("height disagreement", geometry.height_disagreement(rec, alt),
         "<=", geometry.MAX_HEIGHT_DISAGREEMENT),
    ]
    for name, value, op, limit in checks:
        ok = value >= limit if op == ">=" else value <= limit
        print(f"{name:22s} {value:10.4f}  {op} {limit:<8}  {'ok' if ok else 'REFUSED'}")
    print(f"{time.perf_counter() - t0:.0f} s in all")


if __name__ == "__main__":
    main()
