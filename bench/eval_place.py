"""Place recognition on seneca-uav: which global feature finds the right map image.

Each query frame of pass 2 is compared with every map image of pass 1 under one global
feature; a query counts as recalled at k when one of its k most similar map images lies
within 25 m of the query's true position (the nearest map image is within 25 m for 88 % of
the queries: the ceiling). Also the error of the best match alone, mean and median. Query
images as they are and relit (``--variants none,dusk``).

Features: the place descriptors (ORB and RootSIFT, VLAD and bag of words, vocabularies
trained on the pass-1 map), Weiss's WGOH x WGII (normalised intersection), and, for
reference, SIFT match share (Lowe ratio 0.8, no verification: the data set's README floor).
Writes ``bench/results/place.md`` and ``place.json``.

Usage::

    .venv/bin/python bench/eval_place.py [--variants none,dusk] [--no-sift]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # one core, before numpy loads

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from workers.core.experiment import load_experiment  # noqa: E402
from workers.core.features import DESCRIPTOR_NAMES  # noqa: E402
from workers.core.localisers.similarity_models import (  # noqa: E402
    global_similarity,
    sift_similarity,
)

SENECA = ROOT.parent / "shared" / "datasets" / "seneca-uav"
RADIUS_M = 25.0
FEATURES: dict[str, tuple[tuple[str, ...], str]] = {
    **{name: ((name,), "bradley") for name in DESCRIPTOR_NAMES},
    "wgoh x wgii": (("wgoh", "wgii"), "weiss"),
}
"""Row label -> (global features multiplied, measure for the histogram features)."""


def recall(scores: np.ndarray, map_xy: np.ndarray, truth: np.ndarray) -> dict:
    """Recall@1/@5 within RADIUS_M and the error of the best match.

    Parameters
    ----------
    scores : (Q, N) similarities of every query to every map image
    map_xy : (N, 2)
    truth : (Q, 2)
    """
    order = np.argsort(-scores, axis=1, kind="stable")[:, :5]
    d = np.linalg.norm(map_xy[order] - truth[:, None, :], axis=2)
    return {"recall_at_1": float((d[:, 0] <= RADIUS_M).mean()),
            "recall_at_5": float((d <= RADIUS_M).any(axis=1).mean()),
            "mean_error_m": float(d[:, 0].mean()), "median_error_m": float(np.median(d[:, 0]))}


def evaluate_variant(variant: str, *, with_sift: bool, seed: int) -> dict:
    exp = load_experiment(SENECA, map_pass=1, query_pass=2, photometric=variant, seed=seed)
    m = exp.map_data
    xy = np.asarray(m.positions)
    every = np.arange(len(m))
    d_nearest = np.linalg.norm(xy[None] - exp.truth[:, None], axis=2).min(axis=1)
    rows = {"nearest map image (ceiling)": {
        "recall_at_1": float((d_nearest <= RADIUS_M).mean()),
        "recall_at_5": float((d_nearest <= RADIUS_M).mean()),
        "mean_error_m": float(d_nearest.mean()), "median_error_m": float(np.median(d_nearest))}}
    for label, (names, measure) in FEATURES.items():
        scores, ms = [], []
        for q in exp.queries:
            vec, extract_ms = q.global_features(names, m.vocabularies)
            t0 = time.perf_counter()
            scores.append(global_similarity(vec, m, every, features=names, measure=measure))
            ms.append(extract_ms + (time.perf_counter() - t0) * 1e3)
        rows[label] = {**recall(np.stack(scores), xy, exp.truth),
                       "ms_per_query": float(np.median(ms))}
    if with_sift:
        scores = [sift_similarity(q.sift()[0], m, every, ratio=0.8, verify="none")
                  for q in exp.queries]
        rows["sift match share (ratio 0.8)"] = recall(np.stack(scores), xy, exp.truth)
    return {"map_images": len(m), "queries": len(exp.queries), "rows": rows}


def table(result: dict) -> str:
    lines = ["| feature | recall@1 | recall@5 | best match mean / median error (m) | "
             "ms per query (median) |", "|---|---|---|---|---|"]
    for label, r in result["rows"].items():
        ms = f"{r['ms_per_query']:.1f}" if "ms_per_query" in r else "-"
        lines.append(f"| {label} | {100 * r['recall_at_1']:.0f} % | "
                     f"{100 * r['recall_at_5']:.0f} % | {r['mean_error_m']:.1f} / "
                     f"{r['median_error_m']:.1f} | {ms} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--variants", default="none,dusk")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-sift", action="store_true", help="Leave out the SIFT reference row.")
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results")
    args = ap.parse_args()
    if not (SENECA / "images").is_dir():
        sys.exit(f"data set not found: {SENECA}")
    args.out.mkdir(parents=True, exist_ok=True)
    sections = ["# Place recognition on seneca-uav: pass 2 against a map of pass 1", "",
                f"Recall@k: one of the k most similar map images within {RADIUS_M:.0f} m of "
                "the query's true position. Vocabularies trained on the map's own images "
                f"(seed {args.seed}). {platform.machine()}, Python {platform.python_version()}, "
                "one BLAS thread; the times include extracting the frame's features (SIFT "
                "itself for RootSIFT) and scoring all map images.",
                "Command: `.venv/bin/python bench/eval_place.py`.", ""]
    everything = {}
    for variant in args.variants.split(","):
        t0 = time.perf_counter()
        result = evaluate_variant(variant, with_sift=not args.no_sift, seed=args.seed)
        everything[variant] = result
        sections += [f"## Query images: {variant}", "",
                     f"{result['queries']} queries, {result['map_images']} map images.", "",
                     table(result), "", f"({(time.perf_counter() - t0) / 60:.1f} min)", ""]
        print(f"{variant}: done", flush=True)
    (args.out / "place.md").write_text("\n".join(sections))
    (args.out / "place.json").write_text(json.dumps(everything, indent=2))
    print("\n".join(sections))


if __name__ == "__main__":
    main()
