"""The tie points' RANSAC budget: time against the pairs that verify.

A map's tie-point pairs are verified by COLMAP's two-view geometry
(:func:`workers.core.geometry.pairs.match_pair`). A pair that overlaps stops early; one that
does not runs every trial its budget allows, for the fundamental matrix and the homography
both. This measures, over the pairs real map builds plan, the RANSAC CPU time and the pairs
and tie points that verify at several budgets, with and without the cap of
:func:`~workers.core.geometry.pairs.ransac_floor` (the build runs
:data:`~workers.core.geometry.pairs.TIE_RANSAC_TRIALS` with the cap); each pair's variants
run one after the other, so that the machine's load falls alike on all of them.

The maps: seneca-uav pass 1 and lewis-uav's alternate split, as ``vloc eval`` builds them.

    OMP_NUM_THREADS=1 .venv/bin/python bench/bench_tie_ransac.py [--variants 2000,2000c,500]
                                                                 [--out bench/results/tie_ransac.md]

A variant is a budget, capped where it ends in ``c``; the first is the reference. The
variant ``usac`` is not COLMAP's: OpenCV's USAC (MAGSAC++) estimates the fundamental
matrix and the homography (2,000 iterations at most, 4 px, 0.999), and COLMAP's rule for an
uncalibrated pair reads them (:func:`usac_verify`), to see what a faster verification would
cost and change.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np
from _common import DATASETS, RESULTS, machine_and_python, repo_on_path, write_result
from threadpoolctl import threadpool_limits

repo_on_path()

from vloc.workers.core import tiepairs  # noqa: E402
from vloc.workers.core.evaluation.datasets import load_dataset, split  # noqa: E402
from vloc.workers.core.geometry import pairs  # noqa: E402
from vloc.workers.core.geometry.sfm import to_colmap_pixels  # noqa: E402
from vloc.workers.core.sift import ratio_matches  # noqa: E402
from vloc.workers.core.tiepoints import extract_tie_points  # noqa: E402

MAPS = {"seneca-uav pass 1": ("seneca-uav", {"rule": "pass", "map_pass": 1, "query_pass": 2}),
        "lewis-uav alternate": ("lewis-uav", {"rule": "alternate"})}


def verify(m: np.ndarray, ka, kb, a: int, b: int, variant: str,
           ) -> tuple[float, np.ndarray | None]:
    """CPU seconds of one pair's two-view geometry in ``variant`` (a budget of trials,
    capped by :func:`~workers.core.geometry.pairs.ransac_floor` where it ends in ``c``), and
    its inlier matches (None where it does not verify), as the build verifies a pair
    (:func:`~workers.core.geometry.pairs.verify_matches`)."""
    t0 = time.thread_time()
    found = pairs.verify_matches(a, b, ka, kb, m, trials=int(variant.rstrip("c")),
                                 capped=variant.endswith("c"))
    return time.thread_time() - t0, None if found is None else found.matches


def usac_verify(m: np.ndarray, ka, kb, *, min_inliers: int = 15,
                max_h_ratio: float = 0.8) -> tuple[float, np.ndarray | None]:
    """CPU seconds and inlier matches (None where the pair does not verify) of OpenCV's
    USAC (MAGSAC++) fundamental matrix and homography, read by COLMAP's rule for an
    uncalibrated pair: no pair where neither holds ``min_inliers``; the homography's
    inliers where it holds more than ``max_h_ratio`` of the fundamental matrix's and at
    least as many (planar or panoramic), else the fundamental matrix's. No watermark
    test."""
    t0 = time.thread_time()
    p1 = to_colmap_pixels(np.asarray(ka))[m[:, 0]].astype(np.float64)
    p2 = to_colmap_pixels(np.asarray(kb))[m[:, 1]].astype(np.float64)
    _, f_mask = cv2.findFundamentalMat(p1, p2, cv2.USAC_MAGSAC, 4.0, 0.999, 2000)
    _, h_mask = cv2.findHomography(p1, p2, cv2.USAC_MAGSAC, 4.0, maxIters=2000,
                                   confidence=0.999)
    nf = 0 if f_mask is None else int(f_mask.sum())
    nh = 0 if h_mask is None else int(h_mask.sum())
    seconds = time.thread_time() - t0
    if max(nf, nh) < min_inliers:
        return seconds, None
    mask = h_mask if nh > max_h_ratio * nf and nh >= nf else f_mask
    return seconds, m[np.flatnonzero(mask.ravel())]


def measure(name: str, folder: Path, rule: dict, variants: list[str]) -> dict:
    ds = load_dataset(folder)
    images, _ = split(ds, **rule)
    ties = [extract_tie_points(im.path.read_bytes()) for im in images]
    times = [np.nan if im.captured_at is None else im.captured_at.timestamp() for im in images]
    planned = tiepairs.plan([im.lat for im in images], [im.lon for im in images],
                            [im.alt for im in images], times)
    seconds = {v: 0.0 for v in variants}
    inliers = {v: np.zeros(len(planned), np.int64) for v in variants}
    same = {v: 0 for v in variants}
    overlap: dict[str, list[float]] = {v: [] for v in variants}
    ratio_s, tried = 0.0, 0
    for k, (a, b) in enumerate(planned):
        t0 = time.thread_time()
        m = ratio_matches(ties[a].descriptors, ties[b].descriptors)
        ratio_s += time.thread_time() - t0
        if len(m) < 15:
            continue
        tried += 1
        found = {}
        for v in variants:
            if v == "usac":
                s, found[v] = usac_verify(m, ties[a].keypoints, ties[b].keypoints)
            else:
                s, found[v] = verify(m, ties[a].keypoints, ties[b].keypoints, a, b, v)
            seconds[v] += s
            inliers[v][k] = 0 if found[v] is None else len(found[v])
        ref = found[variants[0]]
        for v in variants:
            same[v] += (ref is None and found[v] is None) or (
                ref is not None and found[v] is not None and np.array_equal(ref, found[v]))
            if ref is not None and found[v] is not None:
                a_set, b_set = (set(map(tuple, x.tolist())) for x in (ref, found[v]))
                overlap[v].append(len(a_set & b_set) / len(a_set | b_set))
    return {"name": name, "images": len(images), "pairs": len(planned), "tried": tried,
            "ratio_s": ratio_s, "seconds": seconds, "inliers": inliers, "same": same,
            "overlap": {v: float(np.median(o)) if o else float("nan")
                        for v, o in overlap.items()}}


def label(variant: str) -> str:
    if variant == "usac":
        return "OpenCV USAC (MAGSAC++)"
    return f"{variant.rstrip('c')}, capped" if variant.endswith("c") else variant


def table(rows: list[dict], variants: list[str]) -> str:
    ref = variants[0]
    out = ["| map | pairs (RANSAC run) | trials | RANSAC CPU s | against the first | verified "
           "pairs | lost / gained | pairs as the first's | inlier overlap with the first's | tie "
           "points | ratio test CPU s |",
           "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        base = r["inliers"][ref] > 0
        for v in variants:
            ok = r["inliers"][v] > 0
            out.append(
                f"| {r['name']} ({r['images']} images) | {r['pairs']} ({r['tried']}) "
                f"| {label(v)} | {r['seconds'][v]:.1f} | {r['seconds'][v] / r['seconds'][ref]:.2f} "
                f"| {int(ok.sum())} | {int((base & ~ok).sum())} / {int((~base & ok).sum())} "
                f"| {r['same'][v]} of {r['tried']} | {r['overlap'][v]:.2f} "
                f"| {int(r['inliers'][v].sum()):,} "
                f"| {r['ratio_s']:.1f} |")
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--variants", default="2000,2000c,1000c,500",
                    help="RANSAC trial budgets, capped where they end in c; the reference first")
    ap.add_argument("--out", type=Path, default=RESULTS / "tie_ransac.md")
    args = ap.parse_args()
    variants = args.variants.split(",")
    rows = []
    with threadpool_limits(limits=1):
        for name, (folder, rule) in MAPS.items():
            if not (DATASETS / folder / "images").is_dir():
                print(f"{name}: {DATASETS / folder} absent, skipped")
                continue
            rows.append(measure(name, DATASETS / folder, rule, variants))
            print(table(rows[-1:], variants), flush=True)
    if not rows:
        sys.exit("no data set found")
    text = (f"# The tie points' RANSAC budget\n\n"
            f"`OMP_NUM_THREADS=1 .venv/bin/python bench/bench_tie_ransac.py --variants "
            f"{args.variants}` ({machine_and_python()}, one "
            f"thread; CPU time of the matching thread). The build runs "
            f"{pairs.TIE_RANSAC_TRIALS} trials, capped by the inlier ratio a pair could verify "
            f"with (`pairs.ransac_floor`). Lost / gained: pairs that verify with "
            f"{label(variants[0])} trials and not with these, and the reverse; as the first's: "
            f"pairs whose result (not verified, or every inlier match) is the first's; "
            f"inlier overlap: the median over the pairs both verify of the inlier matches "
            f"they share, of those either keeps.\n\n"
            + table(rows, variants) + "\n")
    write_result(args.out, text, echo=False, announce=True)


if __name__ == "__main__":
    main()
