"""Benchmark: what reporting the cloud's heaviest cluster costs a filter step.

A step of the ``default`` configuration reports the mean of its cloud's heaviest cluster
where that cluster holds most of the weight, and judges its spread
(:mod:`workers.core.pf.clusters`); ``weiss2008`` reports the whole cloud's weighted mean
(:func:`workers.core.pf.filter.cloud_stats`). Both
are timed side by side, in one run, on one core, on clouds shaped as a filter's are after a
fix: most particles around it, the rest strays over the map. Medians of repeated runs.

Usage::

    .venv/bin/python bench/bench_point_estimate.py [--repeats 2000] [--out bench/results/point_estimate.md]
"""

from __future__ import annotations

from _common import RESULTS, one_thread, repo_on_path, write_result

one_thread()

import argparse  # noqa: E402
import os  # noqa: E402
import platform  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

repo_on_path()

from vloc.workers.core.pf.clusters import heaviest_cluster  # noqa: E402
from vloc.workers.core.pf.filter import cloud_stats  # noqa: E402

CELL_M = 10.2
"""seneca-uav's cells: its images' spacing, 28.9 m, over 2 * sqrt(2)."""


def cloud(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``n`` particles: 80 % within a few metres of a fix, 20 % strays over a 1 km map."""
    k = int(0.8 * n)
    xy = np.concatenate([rng.normal(0.0, 4.0, size=(k, 2)),
                         rng.uniform(-500.0, 500.0, size=(n - k, 2))])
    w = np.concatenate([np.full(k, 1.0), np.full(n - k, 0.01)])
    return xy, w / w.sum()


def median_us(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)) * 1e6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=2000)
    ap.add_argument("--out", type=Path, default=RESULTS / "point_estimate.md")
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    rows = []
    for n in (300, 3000, 30000):
        xy, w = cloud(n, rng)
        repeats = max(args.repeats * 300 // n, 20)

        def mean(xy=xy, w=w):
            cloud_stats(xy, w)

        def cluster(xy=xy, w=w):
            cloud_stats(xy, w)  # the switching rule's figures, and the fallback
            members, share = heaviest_cluster(xy, w, CELL_M)
            if share > 0.5:
                own = cloud_stats(xy[members], w[members] / w[members].sum())
                cloud_stats(xy, w, about=own.mean)

        # interleaved, so that both see the same load
        a, b = [], []
        for _ in range(5):
            a.append(median_us(mean, repeats // 5))
            b.append(median_us(cluster, repeats // 5))
        rows.append((n, float(np.median(a)), float(np.median(b))))
        print(rows[-1], flush=True)
    lines = [
        "# The reported position: the whole cloud's mean against the heaviest cluster's",
        "",
        f"`.venv/bin/python bench/bench_point_estimate.py --repeats {args.repeats}` on "
        f"{platform.machine()}, {os.cpu_count()} CPUs, Python {platform.python_version()}, "
        "one thread: the estimate of one filter step, medians of repeated runs, both "
        f"measured side by side; cells of {CELL_M} m (seneca-uav's).",
        "",
        "| particles | weighted mean (`weiss2008`) | heaviest cluster (`default`) | extra per step |",
        "|---|---|---|---|",
    ]
    for n, a, b in rows:
        lines.append(f"| {n:,} | {a:.0f} us | {b:.0f} us | {b - a:.0f} us |")
    lines += ["", "A step of the hybrid on seneca-uav takes 12-15 ms on this machine "
              "(`bench/results/geometry.md`); `default` runs 300 particles.", ""]
    write_result(args.out, "\n".join(lines))


if __name__ == "__main__":
    main()
