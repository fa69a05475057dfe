"""Place recognition on seneca-uav: which global feature finds the right map image.

Each query frame of pass 2 is compared with every map image of pass 1 under one global
feature; a query counts as recalled at k when one of its k most similar map images lies
within 25 m of the query's true position (the nearest map image is within 25 m for 88 % of
the queries: the ceiling). Also the error of the best match alone, mean and median. Query
images as they are and relit (``--variants none,dusk``).

Features: the place descriptors (ORB and RootSIFT, VLAD and bag of words, vocabularies
trained on the pass-1 map), Weiss's WGOH x WGII (normalised intersection), and, for
reference, SIFT match share (Lowe ratio 0.8, no verification: the data set's README floor).
Vocabulary training is random (sampling, k-means++ seeds), so the descriptors are trained
with several seeds and their figures are the mean over seeds, with the range of recall@1.
Writes ``bench/results/place.md`` and ``place.json``.

Usage::

    .venv/bin/python bench/eval_place.py [--variants none,dusk] [--seeds 3] [--no-sift]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from _common import DATASETS, RESULTS, machine_and_python, one_thread, repo_on_path, write_result

one_thread(["OPENBLAS_NUM_THREADS"], override=False)  # one core, before numpy loads

repo_on_path()

import numpy as np  # noqa: E402

from vloc.workers.core.evaluation.datasets import load_dataset, load_frames, split  # noqa: E402
from vloc.workers.core.evaluation.experiment import truth_positions  # noqa: E402
from vloc.workers.core.evaluation.photometric import apply_variant, variant_rng  # noqa: E402
from vloc.workers.core.features import DESCRIPTOR_NAMES  # noqa: E402
from vloc.workers.core.image import prepare  # noqa: E402
from vloc.workers.core.localisers.scoring import (  # noqa: E402
    global_similarity,
    sift_similarity,
)
from vloc.workers.core.mapbuild import assemble_map, extract_image_features  # noqa: E402
from vloc.workers.core.query import QueryFrame  # noqa: E402

SENECA = DATASETS / "seneca-uav"
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


def _scores(queries, m, names, measure) -> tuple[np.ndarray, float]:
    """Similarities of every query to every map image, and the median ms per query."""
    every = np.arange(len(m))
    scores, ms = [], []
    for q in queries:
        vec, extract_ms = q.global_features(names, m.vocabularies)
        t0 = time.perf_counter()
        scores.append(global_similarity(vec, m, every, features=names, measure=measure))
        ms.append(extract_ms + (time.perf_counter() - t0) * 1e3)
    return np.stack(scores), float(np.median(ms))


def evaluate_variant(variant: str, *, with_sift: bool, seeds: int, photometric_seed: int) -> dict:
    ds = load_dataset(SENECA)
    map_images, query_images = split(ds, "pass", map_pass=1, query_pass=2)
    map_feats = [extract_image_features(f) for f in load_frames(map_images)]
    frames = load_frames(query_images)
    if variant != "none":
        frames = [prepare(apply_variant(f.colour, variant, rng=variant_rng(photometric_seed, i)))
                  for i, f in enumerate(frames)]
    queries = [QueryFrame(f, key=i) for i, f in enumerate(frames)]
    maps = [assemble_map(names=[im.name for im in map_images],
                         lats=[im.lat for im in map_images], lons=[im.lon for im in map_images],
                         alts=[im.alt for im in map_images], features=map_feats, seed=seed)
            for seed in range(seeds)]
    xy = np.asarray(maps[0].positions)
    truth = truth_positions(query_images, maps[0])
    d_nearest = np.linalg.norm(xy[None] - truth[:, None], axis=2).min(axis=1)
    rows = {"nearest map image (ceiling)": {
        "recall_at_1": float((d_nearest <= RADIUS_M).mean()),
        "recall_at_5": float((d_nearest <= RADIUS_M).mean()),
        "mean_error_m": float(d_nearest.mean()), "median_error_m": float(np.median(d_nearest))}}
    for label, (names, measure) in FEATURES.items():
        per_seed = []
        for m in (maps if label in DESCRIPTOR_NAMES else maps[:1]):
            scores, ms = _scores(queries, m, names, measure)
            per_seed.append({**recall(scores, xy, truth), "ms_per_query": ms})
        row = {k: float(np.mean([r[k] for r in per_seed])) for k in per_seed[0]}
        row["recall_at_1_range"] = [min(r["recall_at_1"] for r in per_seed),
                                    max(r["recall_at_1"] for r in per_seed)]
        row["seeds"] = len(per_seed)
        rows[label] = row
    if with_sift:
        every = np.arange(len(xy))
        scores = [sift_similarity(q.sift()[0], maps[0], every, ratio=0.8, verify="none")
                  for q in queries]
        rows["sift match share (ratio 0.8)"] = recall(np.stack(scores), xy, truth)
    return {"map_images": len(xy), "queries": len(queries), "rows": rows}


def table(result: dict) -> str:
    lines = ["| feature | recall@1 | recall@1 over seeds | recall@5 | best match mean / median "
             "error (m) | ms per query (median) |", "|---|---|---|---|---|---|"]
    for label, r in result["rows"].items():
        ms = f"{r['ms_per_query']:.1f}" if "ms_per_query" in r else "-"
        lo, hi = r.get("recall_at_1_range", (None, None))
        spread = f"{100 * lo:.0f}-{100 * hi:.0f} % ({r['seeds']})" if r.get("seeds", 1) > 1 \
            else "-"
        lines.append(f"| {label} | {100 * r['recall_at_1']:.0f} % | {spread} | "
                     f"{100 * r['recall_at_5']:.0f} % | {r['mean_error_m']:.1f} / "
                     f"{r['median_error_m']:.1f} | {ms} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--variants", default="none,dusk")
    ap.add_argument("--seed", type=int, default=0, help="Seed of the photometric variant.")
    ap.add_argument("--seeds", type=int, default=3, help="Vocabulary seeds 0..N-1.")
    ap.add_argument("--no-sift", action="store_true", help="Leave out the SIFT reference row.")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args()
    if not (SENECA / "images").is_dir():
        sys.exit(f"data set not found: {SENECA}")
    args.out.mkdir(parents=True, exist_ok=True)
    sections = ["# Place recognition on seneca-uav: pass 2 against a map of pass 1", "",
                f"Recall@k: one of the k most similar map images within {RADIUS_M:.0f} m of "
                "the query's true position. Vocabularies trained on the map's own images "
                f"with seeds 0..{args.seeds - 1}; descriptor rows are means over the seeds. "
                f"{machine_and_python()}, "
                "one BLAS thread; the times include extracting the frame's features (SIFT "
                "itself for RootSIFT) and scoring all map images.",
                "Command: `.venv/bin/python bench/eval_place.py`.", ""]
    everything = {}
    for variant in args.variants.split(","):
        t0 = time.perf_counter()
        result = evaluate_variant(variant, with_sift=not args.no_sift, seeds=args.seeds,
                                  photometric_seed=args.seed)
        everything[variant] = result
        sections += [f"## Query images: {variant}", "",
                     f"{result['queries']} queries, {result['map_images']} map images.", "",
                     table(result), "", f"({(time.perf_counter() - t0) / 60:.1f} min)", ""]
        print(f"{variant}: done", flush=True)
    write_result(args.out / "place.md", "\n".join(sections))
    (args.out / "place.json").write_text(json.dumps(everything, indent=2))


if __name__ == "__main__":
    main()
