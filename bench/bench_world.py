"""Benchmark: how fast the synthetic world generator writes a data set, on one core.

Generates a robot world (street block, three passes: sunny, cloudy, dusk) and a UAV world
(nadir survey, three passes) of ``--frames`` frames per pass, ``--repeats`` times each, and
reports the median wall time split into scene building, shading (textures lit and shadows
baked once per pass), rendering and writing (JPEG + EXIF), plus the time per frame. With
``--full`` it also times one default robot world: a full 260 m round per pass.

Usage::

    .venv/bin/python bench/bench_world.py [--frames 100] [--repeats 3] [--full]
                                          [--out bench/results/world.md]
"""

from __future__ import annotations

from _common import RESULTS, one_thread, repo_on_path, write_result

one_thread()

import argparse  # noqa: E402
import os  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

repo_on_path()

from vloc.clients.world import generate_world  # noqa: E402

PASSES = ["sunny", "cloudy", "dusk"]
STAGES = ("scene", "shading", "rendering", "writing")


def run(kind: str, frames: int | None, seed: int) -> dict:
    with tempfile.TemporaryDirectory(prefix="vloc-world-") as out:
        t0, c0 = time.perf_counter(), time.process_time()
        info = generate_world(out, kind=kind, seed=seed, passes=PASSES, frames=frames)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    return {"wall": wall, "cpu": cpu, "images": info.images, **info.timings,
            "route": info.route_length_m}


def median_row(runs: list[dict]) -> dict:
    return {k: float(np.median([r[k] for r in runs])) for k in runs[0]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--full", action="store_true")
    parser.add_argument("--out", type=Path, default=RESULTS / "world.md")
    args = parser.parse_args()
    cv2.setNumThreads(1)
    rows = []
    for kind in ("robot", "uav"):
        runs = [run(kind, args.frames, seed) for seed in range(args.repeats)]
        rows.append((f"{kind}, {args.frames} frames x 3 passes", median_row(runs)))
        print(rows[-1])
    if args.full:
        rows.append(("robot, full 260 m round x 3 passes", run("robot", None, 0)))
        print(rows[-1])
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    lines = [
        "# Synthetic world generator: speed",
        "",
        f"`{' '.join(['.venv/bin/python', 'bench/bench_world.py'] + sys.argv[1:])}`",
        "",
        f"One core (OpenCV, BLAS and OpenMP limited to one thread); median of {args.repeats} "
        "runs with different seeds (the full round: one run). Wall time includes building the "
        "scene, shading every texture and baking the shadows once per pass, rendering at 2x "
        "and averaging down to 320x240, and writing JPEG + EXIF + CSV.",
        "",
        "| world | images | route (m) | scene (s) | shading (s) | rendering (s) | writing (s) "
        "| wall (s) | CPU (s) | ms per image (wall) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, r in rows:
        lines.append(f"| {name} | {r['images']:.0f} | {r['route']:.0f} | {r['scene']:.2f} | "
                     f"{r['shading']:.2f} | {r['rendering']:.2f} | {r['writing']:.2f} | "
                     f"{r['wall']:.1f} | {r['cpu']:.1f} | {1000 * r['wall'] / r['images']:.0f} |")
    lines += [
        "",
        f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} logical CPUs "
        f"shared with other jobs (1-minute load average {load:.1f} at the end of the run); "
        f"Python {platform.python_version()}, NumPy {np.__version__}, OpenCV {cv2.__version__}.",
        "",
    ]
    write_result(args.out, "\n".join(lines), echo=False, announce=True)


if __name__ == "__main__":
    main()
