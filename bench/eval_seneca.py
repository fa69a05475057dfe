"""The real-data evaluation: seneca-uav, map pass 1, query pass 2 (see its README).

Every localiser under both filter configurations, with the query images as they are and
relit (``--photometric``), averaged over several starting frames; errors over the frames
after the 10th. Writes ``bench/results/seneca.md`` (tables), ``seneca.json`` and
``seneca_tracks.png``.

Usage::

    .venv/bin/python bench/eval_seneca.py [--starts 5] [--variants none,dusk]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from _common import DATASETS, RESULTS, machine_and_python, repo_on_path, write_result

repo_on_path()

from vloc.workers.core.evaluation.evaluate import evaluate, retrieval_grid  # noqa: E402
from vloc.workers.core.evaluation.experiment import load_experiment  # noqa: E402
from vloc.workers.core.evaluation.report import (  # noqa: E402
    grid_table,
    markdown_table,
    plot_tracks,
    results_dict,
)
from vloc.workers.core.features import FEATURE_NAMES  # noqa: E402
from vloc.workers.core.measures import MEASURES  # noqa: E402

SENECA = DATASETS / "seneca-uav"
MODES = ["hybrid", "global", "sift", "hierarchical", "retrieval"]
README_FLOOR = """| method, pass 2 against pass 1 | mean error | median error | within 25 m |
|---|---|---|---|
| nearest map image to the true position (best possible retrieval) | 12.0 m | 9.1 m | 88 % |
| retrieval by WGOH histogram intersection | 89.0 m | 71.4 m | 32 % |
| retrieval by SIFT ratio-test match share | 74.4 m | 19.2 m | 59 % |"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dataset", type=Path, default=SENECA)
    ap.add_argument("--starts", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--variants", default="none,dusk")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args()
    if not (args.dataset / "images").is_dir():
        sys.exit(f"data set not found: {args.dataset}")
    args.out.mkdir(parents=True, exist_ok=True)
    sections = ["# seneca-uav: pass 2 localised against a map of pass 1", "",
                f"{args.starts} starting frames, seed {args.seed}, errors over the frames after "
                f"the 10th of each run. {machine_and_python()}.",
                "Command: `make eval-seneca` (`.venv/bin/python bench/eval_seneca.py`).", "",
                "The data set's own floor (single-frame methods, from its README):", "",
                README_FLOOR, ""]
    everything = {}
    for variant in args.variants.split(","):
        t0 = time.perf_counter()
        exp = load_experiment(args.dataset, map_pass=1, query_pass=2, photometric=variant,
                              seed=args.seed)
        results = evaluate(exp.map_data, exp.queries, exp.truth, modes=MODES,
                           configs=["default", "weiss2008"], starts=args.starts,
                           seed=args.seed)
        data = results_dict(results)
        data["retrieval_grid"] = retrieval_grid(exp.map_data, exp.queries, exp.truth,
                                                features=FEATURE_NAMES, measures=MEASURES,
                                                skip=10)
        everything[variant] = data
        minutes = (time.perf_counter() - t0) / 60
        sections += [f"## Query images: {variant}", "", markdown_table(data), "",
                     "Single-frame retrieval error, mean / median (m), feature x measure "
                     "(Flyphone Fig. 7):", "", grid_table(data["retrieval_grid"]), "",
                     f"({minutes:.1f} min)", ""]
        if variant == "none":
            plot_tracks(args.out / "seneca_tracks.png", exp.map_data.positions,
                        {"default": results["default"]},
                        title="seneca-uav pass 2, default configuration, first start")
        print(f"{variant}: done in {minutes:.1f} min", flush=True)
    write_result(args.out / "seneca.md", "\n".join(sections))
    (args.out / "seneca.json").write_text(json.dumps(everything, indent=2))


if __name__ == "__main__":
    main()
