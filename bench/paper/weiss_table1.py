"""Weiss et al. 2008, Table I and Fig. 4 a-d: global, SIFT and hybrid localisation errors.

Two robot worlds stand in for the paper's two data sets: dataset 1 (a street block; passes
sunny, cloudy, sunny, cloudy) and dataset 2 (another block; passes sunny, dusk, sunny,
dusk: the paper's second "cloudy" condition was an evening, dark and overcast). Each table
row is a train/test pair of illuminations; a same-illumination row maps one pass and
localises the other pass under the same light. Every experiment runs the particle filter
of the paper (config ``weiss2008``: 300 particles, d_global = 5.5 m, d_SIFT = 7.0 m; another
with ``--config``) in the modes ``global`` (WGII x WGOH), ``sift`` and ``hybrid``, from
several starting frames, and reports the mean error ± the standard deviation over runs.

The raw runs go to ``weiss_table1.json``; ``weiss_table2.py`` reads them for Table II.

Usage::

    .venv/bin/python bench/paper/weiss_table1.py [--frames 433] [--route-length 260]
        [--starts 3] [--pairs 2] [--datasets 1,2] [--config weiss2008] [--quick]
        [--out bench/results/paper]
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository

from bench._common import one_thread  # noqa: E402

one_thread()

import argparse  # noqa: E402

import numpy as np  # noqa: E402

from bench.paper import _common as c  # noqa: E402
from vloc.workers.core.evaluation.evaluate import evaluate  # noqa: E402
from vloc.workers.core.pf.config import CONFIGS  # noqa: E402

NAME = "weiss_table1"
MODES = ("global", "sift", "hybrid")
MODE_TITLES = {"global": "WGII + WGOH", "sift": "SIFT", "hybrid": "Hybrid"}
CONFIG = "weiss2008"
PAPER_FILTER = " (the paper's: 300 particles, d_global = 5.5 m, d_SIFT = 7.0 m)"

DATASETS = {
    1: {"seed": 1, "passes": ("sunny", "cloudy", "sunny", "cloudy")},
    2: {"seed": 2, "passes": ("sunny", "dusk", "sunny", "dusk")},
}
"""World seed and passes of each data set (pass 1 is the first name)."""

ROWS = (
    # (set, training, testing, [(map pass, query pass), ...]) in the paper's order
    (1, "sunny", "sunny", [(1, 3), (3, 1)]),
    (1, "cloudy", "cloudy", [(2, 4), (4, 2)]),
    (2, "sunny", "sunny", [(1, 3), (3, 1)]),
    (2, "dusk", "dusk", [(2, 4), (4, 2)]),
    (1, "sunny", "cloudy", [(1, 2), (3, 4)]),
    (1, "cloudy", "sunny", [(2, 1), (4, 3)]),
    (2, "sunny", "dusk", [(1, 2), (3, 4)]),
    (2, "dusk", "sunny", [(2, 1), (4, 3)]),
)

PAPER = {
    # Table I: mean ± std (m) of WGII + WGOH, SIFT, Hybrid; dataset 2's "cloudy" is dusk here
    (1, "sunny", "sunny"): ((3.15, 1.20), (2.15, 0.29), (2.03, 0.22)),
    (1, "cloudy", "cloudy"): ((1.60, 0.26), (2.06, 0.56), (1.59, 0.27)),
    (2, "sunny", "sunny"): ((1.09, 0.06), (1.78, 0.05), (1.09, 0.05)),
    (2, "dusk", "dusk"): ((2.07, 0.76), (2.10, 0.14), (1.80, 0.35)),
    (1, "sunny", "cloudy"): ((3.95, 0.54), (3.27, 0.27), (3.17, 0.32)),
    (1, "cloudy", "sunny"): ((3.85, 0.79), (2.52, 0.17), (3.07, 0.36)),
    (2, "sunny", "dusk"): ((3.64, 0.80), (2.88, 0.20), (2.92, 0.23)),
    (2, "dusk", "sunny"): ((3.45, 0.32), (2.74, 0.24), (2.78, 0.22)),
}


def condition(train: str, test: str) -> str:
    return "constant" if train == test else "changing"


def run_pairs(args: argparse.Namespace) -> list[dict]:
    """Evaluate every selected pass pair; one record per pair with the runs of each mode."""
    pairs = []
    for ds in args.datasets:
        spec = DATASETS[ds]
        folder = c.world("robot", seed=spec["seed"], passes=spec["passes"],
                         frames=args.frames, route_length=args.route_length, cache=args.cache)
        for set_, train, test, pass_pairs in ROWS:
            if set_ != ds:
                continue
            for map_pass, query_pass in pass_pairs[: args.pairs]:
                label = f"set {ds} {train}->{test} (pass {map_pass}->{query_pass})"
                c.log(label)
                exp = c.experiment(folder, map_pass, query_pass, config=args.config)
                res = evaluate(exp.map_data, exp.queries, exp.truth, modes=list(MODES),
                               configs=[args.config], starts=args.starts, seed=args.seed,
                               skip=args.skip, progress=c.progress_printer(label))
                runs = c.records(res, args.config)
                pairs.append({"set": ds, "train": train, "test": test, "map_pass": map_pass,
                              "query_pass": query_pass, "runs": runs})
                c.log("  mean error " + ", ".join(
                    f"{m} {c.pool(runs[m], args.skip)['mean_error_m']:.2f} m" for m in MODES))
    return pairs


def rows(pairs: list[dict], skip: int) -> list[dict]:
    """Table I rows: each mode's runs pooled over the pass pairs of a row."""
    out = []
    for set_, train, test, _ in ROWS:
        chosen = [p for p in pairs if (p["set"], p["train"], p["test"]) == (set_, train, test)]
        if not chosen:
            continue
        out.append({"set": set_, "train": train, "test": test,
                    "pairs": [[p["map_pass"], p["query_pass"]] for p in chosen],
                    "modes": {m: c.pool(sum((p["runs"][m] for p in chosen), []), skip)
                              for m in MODES}})
    return out


def table(table_rows: list[dict]) -> str:
    head = ("| set | training | test | pairs | " + " | ".join(
        f"{MODE_TITLES[m]} (ours) | {MODE_TITLES[m]} (paper)" for m in MODES) + " |")
    lines = [head, "|---|---|---|---|" + "---:|" * (2 * len(MODES))]
    for r in table_rows:
        paper = PAPER[(r["set"], r["train"], r["test"])]
        cells = []
        for m, (pm_mean, pm_std) in zip(MODES, paper, strict=True):
            d = r["modes"][m]
            cells += [c.pm(d["mean_error_m"], d["std_error_m"]), c.pm(pm_mean, pm_std)]
        pairs = ", ".join(f"{a}->{b}" for a, b in r["pairs"])
        lines.append(f"| {r['set']} | {r['train']} | {r['test']} | {pairs} | "
                     + " | ".join(cells) + " |")
    return "\n".join(lines)


def averages(table_rows: list[dict]) -> dict:
    """Hybrid minus SIFT mean error, over all rows and over changing-light rows (paper:
    -0.13 m and +0.13 m)."""
    def diff(rs):
        d = [r["modes"]["hybrid"]["mean_error_m"] - r["modes"]["sift"]["mean_error_m"] for r in rs]
        return float(np.mean(d)) if d else float("nan")

    changing = [r for r in table_rows if r["train"] != r["test"]]
    return {"hybrid_minus_sift_all_m": diff(table_rows),
            "hybrid_minus_sift_changing_m": diff(changing)}


def plot(pairs: list[dict], path: Path) -> None:
    """Fig. 4 a-d: mean error against frames since the start, per data set and condition."""
    plt = c.pyplot()
    panels = [(ds, cond) for cond in ("constant", "changing") for ds in sorted(DATASETS)
              if any(p["set"] == ds and condition(p["train"], p["test"]) == cond for p in pairs)]
    cols = min(2, max(1, len(panels)))
    nrows = max(1, -(-len(panels) // cols))
    fig, axes = plt.subplots(nrows, cols, figsize=(5.2 * cols, 3.6 * nrows), dpi=110,
                             squeeze=False)
    for ax, (ds, cond) in zip(axes.ravel(), panels, strict=False):
        chosen = [p for p in pairs if p["set"] == ds and condition(p["train"], p["test"]) == cond]
        for m in MODES:
            curve = c.error_curve(sum((p["runs"][m] for p in chosen), []))
            ax.plot(np.arange(len(curve)), curve, lw=1.2, label=MODE_TITLES[m])
        ax.set_title(f"dataset {ds}, {cond} illumination", fontsize=9)
        ax.set_xlabel("frames since start")
        ax.set_ylabel("mean error (m)")
        ax.set_yscale("log")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


def markdown(args: argparse.Namespace, table_rows: list[dict], avg: dict) -> str:
    return f"""# Weiss et al. 2008, Table I: mean localisation error ± std (m)

Robot worlds from `clients.world` (`kind="robot"`): dataset 1 = seed {DATASETS[1]['seed']}, passes
{", ".join(DATASETS[1]['passes'])}; dataset 2 = seed {DATASETS[2]['seed']}, passes
{", ".join(DATASETS[2]['passes'])} (the paper's dataset 2 "cloudy" rounds were taken in the
evening, overcast and getting dark: `dusk` here). {args.frames} frames per pass on a
{args.route_length:g} m round ({args.route_length / args.frames:.2f} m apart; the paper: about
400 images on 260 m). Filter `{args.config}`{PAPER_FILTER if args.config == CONFIG else ""},
{args.starts} starting frames per pass pair, up to {args.pairs} pass pair(s) per row; the first
{args.skip} frames of each run are left out of the errors; ± is the standard deviation of
the per-run mean errors. Map images are positioned by their EXIF GPS (pass 1: truth + 0.5 m
noise, other passes: truth), as a mapping run would tag them.

{table(table_rows)}

Hybrid minus SIFT, mean over rows: {c.num(avg['hybrid_minus_sift_all_m'])} m (paper: -0.13 m);
over the changing-illumination rows: {c.num(avg['hybrid_minus_sift_changing_m'])} m (paper: +0.13 m).

![error curves](weiss_table1.png)

Fig. 4 a-d analogue: mean error against frames since the start (log scale).

Run: `{' '.join(args.argv)}` in {c.elapsed() / 60:.1f} min. Machine: {c.machine()}.
Table II (SIFT steps, time per frame, speed-up) from the same runs: `weiss_table2.md`.
"""


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    c.size_arguments(parser)
    parser.add_argument("--pairs", type=int, default=2, choices=(1, 2),
                        help="pass pairs per row (2: both ways round, as in the paper's "
                             "all combinations of rounds; 1: half the time)")
    parser.add_argument("--datasets", default="1,2", help="comma-separated data sets")
    parser.add_argument("--config", default=CONFIG, choices=sorted(CONFIGS),
                        help=f"filter configuration (default {CONFIG}, the paper's)")
    args = c.resolve_sizes(parser.parse_args(argv))
    args.argv = ["bench/paper/weiss_table1.py", *(sys.argv[1:] if argv is None else argv)]
    args.datasets = [int(d) for d in args.datasets.split(",")]
    pairs = run_pairs(args)
    table_rows = rows(pairs, args.skip)
    avg = averages(table_rows)
    data = {"sizes": {"frames": args.frames, "route_length_m": args.route_length,
                      "starts": args.starts, "pairs_per_row": args.pairs, "skip": args.skip,
                      "seed": args.seed, "config": args.config, "datasets": DATASETS},
            "seconds": c.elapsed(), "command": " ".join(args.argv), "machine": c.machine(),
            "rows": table_rows, "averages": avg, "pairs": pairs}
    plot(pairs, Path(args.out) / f"{NAME}.png")
    c.write(args.out, NAME, markdown(args, table_rows, avg), data)
    return data


if __name__ == "__main__":
    main()
