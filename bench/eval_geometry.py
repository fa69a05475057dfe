"""The map-geometry acceptance set: real surveys and synthetic worlds that break planes.

For each survey: build its map as `vloc eval` does, report what became of its camera
geometry (COLMAP's reconstruction, aligned to GPS) and what the map measured of itself
(its own images localised against the rest), then localise the query sequence with the
default `hybrid` and `sift` filters and set the self-check's figure beside the error the
evaluation measures. Writes ``bench/results/geometry.md`` and ``geometry.json``.

The surveys:

- seneca-uav, pass 2 against pass 1 (nadir, flat farmland), 5 starts;
- lewis-uav, alternate split (oblique, buildings, gaps), 3 starts, skip 3;
- the robot world (street level, a camera 1 m above the road), `default`;
- the UAV world flat, with 40 m hills, and with GPS altitudes drifting 100 m over the flight.

Usage::

    OMP_NUM_THREADS=1 .venv/bin/python bench/eval_geometry.py [--only seneca,lewis] [--seed 0]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from _common import DATASETS, RESULTS, ROOT, machine_and_python, repo_on_path, write_result

repo_on_path()

from threadpoolctl import threadpool_limits  # noqa: E402

from vloc.clients.world import generate_world  # noqa: E402
from vloc.workers.core.evaluation.evaluate import evaluate  # noqa: E402
from vloc.workers.core.evaluation.experiment import load_experiment  # noqa: E402
from vloc.workers.core.evaluation.report import results_dict  # noqa: E402

WORLDS = ROOT / "bench" / ".cache" / "geometry-worlds"

# name -> (folder or world options, split, starts, skip)
CASES = {
    "seneca": (DATASETS / "seneca-uav", {"rule": "pass", "map_pass": 1, "query_pass": 2}, 5, 10),
    "lewis": (DATASETS / "lewis-uav", {"rule": "alternate"}, 3, 3),
    "robot": ({"kind": "robot"}, {"rule": "pass", "map_pass": 1, "query_pass": 2}, 3, 10),
    "uav-flat": ({"kind": "uav"}, {"rule": "pass", "map_pass": 1, "query_pass": 2}, 3, 10),
    "uav-relief": ({"kind": "uav", "relief_m": 40.0},
                   {"rule": "pass", "map_pass": 1, "query_pass": 2}, 3, 10),
    "uav-drift": ({"kind": "uav", "altitude_drift_m": 100.0},
                  {"rule": "pass", "map_pass": 1, "query_pass": 2}, 3, 10),
}


def folder_of(name: str, source) -> Path | None:
    """The case's images: the shared data set, or its world generated once (seed 0)."""
    if isinstance(source, Path):
        return source if (source / "images").is_dir() else None
    out = WORLDS / name
    if not (out / "world.json").is_file():
        generate_world(out, passes=("sunny", "cloudy"), seed=0, overwrite=True, **source)
    return out


def run_case(name: str, folder: Path, split: dict, starts: int, skip: int,
             build_seed: int = 0) -> dict:
    t0 = time.perf_counter()
    exp = load_experiment(folder, **split, build_seed=build_seed)
    build_s = time.perf_counter() - t0
    report = exp.geometry or {"status": "none"}
    results = evaluate(exp.map_data, exp.queries, exp.truth, modes=["hybrid", "sift"],
                       configs=["default"], starts=starts, skip=skip)
    modes = results_dict(results)["modes"]
    return {"name": name, "map_images": len(exp.map_data), "queries": len(exp.queries),
            "starts": starts, "skip": skip, "build_s": build_s, "geometry": report,
            "modes": modes}


def table(rows: list[dict]) -> str:
    out = ["| survey | geometry | placed | GPS RMS h / v (m) | self-check mean / median (m), "
           "registered | hybrid mean / median (m) | sift mean / median (m) | SIFT steps | "
           "hybrid speed-up | self-check / hybrid mean |",
           "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        g, h, s = r["geometry"], r["modes"]["hybrid"], r["modes"]["sift"]
        check = g.get("self_check") or {}
        placed = f"{g.get('placed', 0)} / {r['map_images']}"
        rms = (f"{g['gps_rms_m']:.1f} / {g['gps_rms_vertical_m'] or float('nan'):.1f}"
               if g.get("gps_rms_m") is not None else "-")
        sc = (f"{check['mean_m']:.1f} / {check['median_m']:.1f}, {check['registered']:.0%}"
              if check.get("mean_m") is not None else "-")
        ratio = (f"{check['mean_m'] / h['mean_error_m']:.2f}" if check.get("mean_m") else "-")
        out.append(
            f"| {r['name']} | {g['status']} | {placed} | {rms} | {sc} | "
            f"{h['mean_error_m']:.1f} / {h['median_error_m']:.1f} | "
            f"{s['mean_error_m']:.1f} / {s['median_error_m']:.1f} | "
            f"{h['sift_step_share']:.0%} | {h['speedup_vs_sift']:.2f}x | {ratio} |")
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", default=",".join(CASES))
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--seed", type=int, default=0,
                    help="the maps' build seed: another shows the spread the build's chance "
                         "alone gives")
    args = ap.parse_args()
    rows = []
    with threadpool_limits(limits=1):
        for name in args.only.split(","):
            source, split, starts, skip = CASES[name]
            folder = folder_of(name, source)
            if folder is None:
                print(f"{name}: data set not found, skipped", file=sys.stderr)
                continue
            row = run_case(name, folder, split, starts, skip, build_seed=args.seed)
            rows.append(row)
            print(table([row]).splitlines()[-1], flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    text = "\n".join([
        "# Map geometry: real surveys and worlds that break planes", "",
        f"{machine_and_python()}, one BLAS thread. Command: "
        f"`OMP_NUM_THREADS=1 .venv/bin/python bench/eval_geometry.py --only {args.only} "
        f"--seed {args.seed}`.",
        "Default configuration; errors over the frames after each run's `skip`; speed-up is "
        "`sift`'s time per frame over `hybrid`'s, measured in the same run.", "",
        table(rows), ""])
    write_result(args.out / "geometry.md", text)
    (args.out / "geometry.json").write_text(json.dumps(rows, indent=1, default=float))


if __name__ == "__main__":
    main()
