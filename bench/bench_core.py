"""Benchmark: SIFT extraction and matching, and one filter step of each kind, on one core.

Uses the real UAV data set when present (map pass 1; frames of pass 2), else a synthetic
world. Every figure is the median over repeated runs; the global/SIFT step ratio is taken
side by side in the same run.

Usage::

    .venv/bin/python bench/bench_core.py [--repeats 30] [--out bench/results/core.md]
"""

from __future__ import annotations

from _common import DATASETS, RESULTS, one_thread, repo_on_path, write_result

one_thread()

import argparse  # noqa: E402
import platform  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

repo_on_path()

from vloc.workers.core.evaluation.experiment import load_experiment  # noqa: E402
from vloc.workers.core.localisers import make_localiser  # noqa: E402
from vloc.workers.core.query import QueryFrame  # noqa: E402
from vloc.workers.core.sift import extract_sift, ratio_matches  # noqa: E402

SENECA = DATASETS / "seneca-uav"


def median_ms(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return float(np.median(times))


def dataset() -> tuple[Path, dict]:
    if (SENECA / "images").is_dir():
        return SENECA, {"map_pass": 1, "query_pass": 2}
    from vloc.clients.world import generate_world

    out = Path(tempfile.mkdtemp(prefix="vloc-bench-"))
    generate_world(out, kind="robot", seed=1, passes=["sunny", "cloudy"], frames=200)
    return out, {"map_pass": 1, "query_pass": 2}


def step_time(exp, mode: str, config: str, kind: str, repeats: int) -> float:
    """Median ms of a filter step pinned to ``kind`` on fresh frames (features included)."""
    loc = make_localiser("global" if kind == "global" else "sift", exp.map_data,
                         {"config": config}, seed=0)
    frames = exp.queries
    times = []
    for r in range(repeats):
        q = frames[r % len(frames)]
        fresh = QueryFrame(q.frame, q.captured_at)  # no cached features: honest timing
        times.append(loc.step(fresh).processing_ms)
    return float(np.median(times))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--out", type=Path, default=RESULTS / "core.md")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    folder, split = dataset()
    exp = load_experiment(folder, **split)
    grey = exp.queries[0].frame.grey
    a = extract_sift(grey)
    b = extract_sift(exp.queries[1].frame.grey)
    rows = [
        ("SIFT extract (320x240)", median_ms(lambda: extract_sift(grey), args.repeats),
         f"{len(a)} keypoints"),
        ("SIFT ratio-test match, one pair", median_ms(
            lambda: ratio_matches(a.descriptors, b.descriptors), args.repeats * 10),
         f"{len(a)} x {len(b)} descriptors"),
    ]
    for config in ("weiss2008", "default"):
        g = step_time(exp, "global", config, "global", args.repeats)
        s = step_time(exp, "sift", config, "sift", args.repeats)
        rows.append((f"filter step, global features ({config})", g,
                     f"{len(exp.map_data)}-image map, 300 particles"))
        rows.append((f"filter step, SIFT ({config})", s, f"SIFT/global = {s / g:.1f}x"))
    lines = [f"# Core stage timings ({folder.name})", "",
             f"Median of {args.repeats} runs (matching: {args.repeats * 10}), one thread; "
             f"{platform.processor() or platform.machine()}, Python {platform.python_version()}, "
             f"OpenCV {cv2.__version__}. Steps include feature extraction of the frame.", "",
             "| stage | ms | note |", "|---|---|---|"]
    lines += [f"| {name} | {ms:.2f} | {note} |" for name, ms, note in rows]
    text = "\n".join(lines) + "\n"
    write_result(args.out, text)


if __name__ == "__main__":
    main()
