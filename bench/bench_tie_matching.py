"""Benchmark: the tie points' ratio test, exact against approximate nearest neighbours.

A build matches the tie points (up to 3,000 SIFT an image) of every planned pair of map
images, most of its matching time: :func:`workers.core.sift.ratio_matches` runs one
3,000 x 3,000 x 128 product a pair. An approximate search (OpenCV's FLANN, randomised
k-d trees) is the usual lever for large descriptor sets; this measures whether it is one at
a pair's size. Pairs of consecutive seneca-uav pass-1 images, both ways timed side by side
in one process, every thread pool pinned to one thread; per method the median CPU time a
pair (``time.thread_time``, median over repeats, then over pairs) and the share of the exact
ratio-test matches it finds too.

Usage::

    .venv/bin/python bench/bench_tie_matching.py [--pairs 8] [--repeats 5]

Writes ``bench/results/tie_matching.md`` and prints it.
"""

from __future__ import annotations

from _common import DATASETS, RESULTS, machine_and_python, one_thread, repo_on_path, write_result

one_thread()

import argparse  # noqa: E402
import os  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

repo_on_path()

from vloc.workers.core.evaluation.datasets import load_dataset, read_image  # noqa: E402
from vloc.workers.core.sift import ratio_matches  # noqa: E402
from vloc.workers.core.tiepoints import extract_tie_points  # noqa: E402

SENECA = DATASETS / "seneca-uav"
RATIO = 0.8
FLANN = ((4, 32), (4, 64), (8, 128))
"""(trees, checks) of the approximate searches tried."""


def flann_matches(a: np.ndarray, b: np.ndarray, trees: int, checks: int) -> np.ndarray:
    """Ratio-test matches from ``a`` into ``b`` by FLANN's randomised k-d trees."""
    matcher = cv2.FlannBasedMatcher({"algorithm": 1, "trees": trees}, {"checks": checks})
    pairs = matcher.knnMatch(a.astype(np.float32), b.astype(np.float32), k=2)
    kept = [(m[0].queryIdx, m[0].trainIdx) for m in pairs
            if len(m) == 2 and m[0].distance < RATIO * m[1].distance]
    return np.asarray(kept, np.int64).reshape(-1, 2)


def cpu_ms(fn, repeats: int) -> tuple[float, np.ndarray]:
    times, out = [], None
    for _ in range(repeats):
        t0 = time.thread_time()
        out = fn()
        times.append((time.thread_time() - t0) * 1e3)
    return float(np.median(times)), out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--out", type=Path, default=RESULTS / "tie_matching.md")
    args = parser.parse_args()
    cv2.setNumThreads(1)
    images = [im for im in load_dataset(SENECA).images if im.pass_ == 1][: args.pairs + 1]
    ties = [extract_tie_points(read_image(im)) for im in images]
    methods = {"exact (`sift.ratio_matches`)": lambda a, b: ratio_matches(a, b, ratio=RATIO)}
    for trees, checks in FLANN:
        methods[f"FLANN, {trees} trees, {checks} checks"] = (
            lambda a, b, t=trees, c=checks: flann_matches(a, b, t, c))
    ms: dict[str, list[float]] = {m: [] for m in methods}
    found: dict[str, list[float]] = {m: [] for m in methods}
    sizes = []
    for first, second in zip(ties, ties[1:], strict=False):
        a, b = first.descriptors, second.descriptors
        sizes.append((len(a), len(b)))
        exact = None
        for name, fn in methods.items():  # side by side, pair by pair
            t, m = cpu_ms(lambda fn=fn, a=a, b=b: fn(a, b), args.repeats)
            exact = m if exact is None else exact
            ms[name].append(t)
            want = set(map(tuple, exact.tolist()))
            found[name].append(len(want & set(map(tuple, m.tolist()))) / max(len(want), 1))
    base = float(np.median(ms[next(iter(methods))]))
    lines = ["# The tie points' ratio test: exact against approximate nearest neighbours", "",
             f"{machine_and_python()}, OpenCV "
             f"{cv2.__version__}, NumPy {np.__version__}; one thread; {len(sizes)} pairs of "
             f"consecutive seneca-uav pass-1 images, {int(np.median([s[0] for s in sizes]))} "
             f"tie points an image (median); median of {args.repeats} runs a pair, then over "
             f"the pairs; load average at the end {os.getloadavg()[0]:.1f} on "
             f"{os.cpu_count()} CPUs.",
             f"Command: `.venv/bin/python bench/bench_tie_matching.py --pairs {args.pairs} "
             f"--repeats {args.repeats}`.", "",
             "| method | CPU ms a pair | against exact | exact matches found |",
             "|---|---|---|---|"]
    for name in methods:
        t = float(np.median(ms[name]))
        lines.append(f"| {name} | {t:.1f} | {t / base:.2f}x | "
                     f"{100 * float(np.mean(found[name])):.1f} % |")
    text = "\n".join(lines) + "\n"
    write_result(args.out, text)


if __name__ == "__main__":
    main()
