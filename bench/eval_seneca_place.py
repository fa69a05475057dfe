"""The filter on seneca-uav with a place descriptor as its global feature.

Map pass 1, query pass 2, ``default`` configuration, 5 starting frames, errors over the frames
after the 10th (as ``bench/eval_seneca.py``). Rows: ``sift`` alone; the ``default`` hybrid as
it is (WGOH x WGII); the hybrid and the global-only filter with ``vlad_orb`` (global power 5,
which suits cosine similarities) under the ``default`` trust gate, a lower gate, and the
paper's switching rule alone (no gate). Query images as they are and relit. Speed-up is
``sift``'s milliseconds per frame over the row's, in the same run. Writes
``bench/results/seneca_place.md`` and ``seneca_place.json``.

Each row is also one ``vloc eval`` call, e.g.::

    .venv/bin/vloc eval ../shared/datasets/seneca-uav --map-pass 1 --query-pass 2 \\
        --modes hybrid,global,sift --param global_features=vlad_orb --param global_power=5

Usage::

    .venv/bin/python bench/eval_seneca_place.py [--starts 5] [--variants none,dusk]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

from _common import DATASETS, RESULTS, machine_and_python, one_thread, repo_on_path, write_result

one_thread(["OPENBLAS_NUM_THREADS"], override=False)  # one core, before numpy loads

repo_on_path()

from vloc.workers.core.evaluation.evaluate import evaluate  # noqa: E402
from vloc.workers.core.evaluation.experiment import load_experiment  # noqa: E402

SENECA = DATASETS / "seneca-uav"
VLAD = {"global_features": ["vlad_orb"], "global_power": 5.0}
ROWS: tuple[tuple[str, str, dict], ...] = (
    ("sift", "sift", {}),
    ("hybrid, WGOH x WGII (default as it is)", "hybrid", {}),
    ("hybrid, vlad_orb", "hybrid", VLAD),
    ("hybrid, vlad_orb, global_trust_level 0.8", "hybrid", {**VLAD, "global_trust_level": 0.8}),
    ("hybrid, vlad_orb, no trust gate (paper rule)", "hybrid", {**VLAD, "global_trust": 0}),
    ("global, vlad_orb", "global", VLAD),
    ("global, WGOH x WGII", "global", {}),
)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--starts", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--variants", default="none,dusk")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args()
    if not (SENECA / "images").is_dir():
        sys.exit(f"data set not found: {SENECA}")
    lines = ["# seneca-uav: the filter with a place descriptor as its global feature", "",
             f"Map pass 1, queries pass 2, `default` configuration with the overrides named, "
             f"{args.starts} starts, seed {args.seed}, errors over the frames after the 10th. "
             f"{machine_and_python()}, one BLAS thread; "
             f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} shared CPUs, so "
             "the milliseconds are wall clock under load: compare them within a table.",
             "Command: `.venv/bin/python bench/eval_seneca_place.py`.", ""]
    everything = {}
    for variant in args.variants.split(","):
        exp = load_experiment(SENECA, map_pass=1, query_pass=2, photometric=variant,
                              seed=args.seed)
        rows = {}
        for label, mode, params in ROWS:
            res = evaluate(exp.map_data, exp.queries, exp.truth, modes=[mode],
                           configs=["default"], starts=args.starts, seed=args.seed,
                           params=dict(params))
            rows[label] = {"mode": mode, "params": params,
                           **res["default"][mode].to_dict()}
            print(f"{variant}: {label} done", flush=True)
        base = rows["sift"]["ms_per_frame"]
        table = ["| filter | mean err (m) | median (m) | within 25 m | SIFT steps | ms/frame | "
                 "ms global | ms SIFT | speed-up vs sift |", "|---|---|---|---|---|---|---|---|---|"]
        for label, r in rows.items():
            r["speedup_vs_sift"] = base / r["ms_per_frame"]

            def f(v):
                return "-" if v is None else f"{v:.1f}"

            table.append(f"| {label} | {r['mean_error_m']:.1f} | {r['median_error_m']:.1f} | "
                         f"{100 * r['within_25m']:.0f} % | {100 * r['sift_step_share']:.1f} % | "
                         f"{r['ms_per_frame']:.1f} | {f(r['ms_per_global_step'])} | "
                         f"{f(r['ms_per_sift_step'])} | {r['speedup_vs_sift']:.2f} |")
        everything[variant] = rows
        lines += [f"## Query images: {variant}", ""] + table + [""]
    write_result(args.out / "seneca_place.md", "\n".join(lines))
    (args.out / "seneca_place.json").write_text(json.dumps(everything, indent=2))


if __name__ == "__main__":
    start = time.perf_counter()
    main()
    print(f"({(time.perf_counter() - start) / 60:.1f} min)")
