"""A map build's CPU, stage by stage, for this checkout and an earlier one side by side.

Each build runs in a fresh process of one BLAS and OpenCV thread (the engine's workers'
setting), alternating between the checkouts so that a shared machine's load falls on both
alike; the figures are the median of the repeats. Two maps: the service tests' ten images
(``tests/app/imagery.py``: what most of the test suite's builds are) and seneca-uav's first
pass (70 real images), when ``../shared`` is there.

Usage::

    .venv/bin/python bench/bench_build_cpu.py [--baseline PKG] [--repeats 5]
        [--seneca-repeats 2] [--out bench/results/build_cpu.md]

``PKG`` is a folder holding the earlier checkout as ``vloc`` (a link to a worktree:
``git worktree add /tmp/base/wt <rev>; ln -s /tmp/base/wt /tmp/base/pkg/vloc``).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from _common import DATASETS, RESULTS, repo_on_path, write_result

SENECA = DATASETS / "seneca-uav"

CHILD = """
import json, sys, time
from threadpoolctl import threadpool_limits
threadpool_limits(1)
import cv2
cv2.setNumThreads(1)
from vloc.workers.core.evaluation.datasets import load_dataset, load_frames, split
from vloc.workers.core.evaluation.experiment import build_map

folder, map_pass = sys.argv[1], int(sys.argv[2])
ds = load_dataset(folder)
images = split(ds, "pass", map_pass=map_pass, query_pass=map_pass + 1)[0] if map_pass \\
    else ds.images
timings, report = {}, {}
t0 = time.process_time()
frames = load_frames(images)
build_map(images, frames, timings=timings, report=report)
total = time.process_time() - t0
print(json.dumps({"total": total, "stages": {k: v[1] for k, v in timings.items()},
                  "placed": report.get("placed"), "status": report.get("status")}))
"""


def build_once(folder: Path, map_pass: int, pkg: Path | None) -> dict:
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1",
               MKL_NUM_THREADS="1")
    if pkg is not None:
        env["PYTHONPATH"] = str(pkg)
    out = subprocess.run([sys.executable, "-c", CHILD, str(folder), str(map_pass)],
                         cwd=tempfile.gettempdir(), env=env, capture_output=True, text=True,
                         check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_images(folder: Path) -> Path:
    """The service tests' ten map images, written as a data set."""
    repo_on_path()
    from tests.app.imagery import map_and_queries

    (folder / "images").mkdir(parents=True, exist_ok=True)
    for shot in map_and_queries(10)[0]:
        (folder / "images" / f"{shot.name}.jpg").write_bytes(shot.jpeg)
    return folder


def median_row(runs: list[dict]) -> dict:
    stages = sorted({k for r in runs for k in r["stages"]})
    return {"total": statistics.median(r["total"] for r in runs),
            "stages": {k: statistics.median(r["stages"].get(k, 0.0) for r in runs)
                       for k in stages},
            "placed": runs[0]["placed"], "status": runs[0]["status"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--baseline", type=Path, help="folder holding an earlier checkout as vloc")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--seneca-repeats", type=int, default=2)
    ap.add_argument("--out", type=Path, default=RESULTS / "build_cpu.md")
    args = ap.parse_args()

    work = Path(tempfile.mkdtemp(prefix="build-cpu-"))
    maps = [("service tests' 10 images", test_images(work / "tests"), 0, args.repeats)]
    if SENECA.is_dir():
        maps.append(("seneca-uav pass 1 (70 images)", SENECA, 1, args.seneca_repeats))
    variants = [("this checkout", None)] + ([("baseline", args.baseline)]
                                             if args.baseline else [])
    results: dict[str, dict[str, dict]] = {}
    for title, folder, map_pass, repeats in maps:
        runs: dict[str, list[dict]] = {name: [] for name, _ in variants}
        for i in range(repeats):
            for name, pkg in (variants if i % 2 == 0 else variants[::-1]):
                runs[name].append(build_once(folder, map_pass, pkg))
                print(f"{title}: {name} run {i + 1}/{repeats}: "
                      f"{runs[name][-1]['total']:.2f} CPU s", flush=True)
        results[title] = {name: median_row(r) for name, r in runs.items()}

    lines = ["# A map build's CPU, stage by stage", "",
             f"`{' '.join(['.venv/bin/python', 'bench/bench_build_cpu.py', *sys.argv[1:]])}`",
             "", "CPU seconds of one process (one BLAS and OpenCV thread), median of the "
             "repeats, the checkouts alternating; the stages are the packing's own "
             "(`assemble_map`'s timings), the total includes decoding and extraction.", ""]
    for title, by_variant in results.items():
        stages = sorted({k for v in by_variant.values() for k in v["stages"]})
        lines += [f"## {title}", "",
                  "| checkout | total CPU s | " + " | ".join(stages) + " | cameras placed |",
                  "|---|---|" + "---|" * len(stages) + "---|"]
        for name, row in by_variant.items():
            lines.append(f"| {name} | {row['total']:.2f} | "
                         + " | ".join(f"{row['stages'][k]:.2f}" for k in stages)
                         + f" | {row['placed']} |")
        if "baseline" in by_variant:
            ratio = by_variant["this checkout"]["total"] / by_variant["baseline"]["total"]
            lines += ["", f"This checkout's build takes {ratio:.2f} of the baseline's CPU."]
        lines.append("")
    write_result(args.out, "\n".join(lines))


if __name__ == "__main__":
    main()
