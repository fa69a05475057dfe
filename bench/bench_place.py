"""Benchmark: the place descriptors' global step and vocabulary training, on one core.

* Global step: a frame's features extracted (ORB, or SIFT for RootSIFT), described against
  the vocabulary and scored against every image of a 1,000-image map (one matrix-vector
  product), from a fresh frame each time; WGOH x WGII alongside for reference. Target:
  8 ms at 320x240.
* Vocabulary training per 1,000 map images, and describing the 1,000 images with the new
  vocabulary (both happen at every map build). Target: 10 s for the training.

The 1,000 map images are views cut from the seneca-uav photographs (random centre, heading
and scale, so that no two are alike), prepared at 320x240 like any map image; the query
frames are pass 2 of the flight. Medians over the query frames and repeated runs. Threads
are pinned to one (BLAS, OpenCV and the process's CPU affinity) before numpy and OpenCV load.
Times are the thread's CPU time (``time.thread_time``): on a machine shared with other work a
wall clock also counts the time the process waits for the CPU, which says nothing about the
step; the wall-clock median of the whole step is given beside it.

Usage::

    .venv/bin/python bench/bench_place.py [--map-images 1000] [--queries 40] [--repeats 3]

Writes ``bench/results/place_timing.md`` and prints it.
"""

from __future__ import annotations

import os

from _common import DATASETS, RESULTS, one_thread, repo_on_path, write_result

one_thread()
if hasattr(os, "sched_setaffinity"):
    os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[-1]})

import argparse  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

cv2.setNumThreads(1)

repo_on_path()

from vloc.workers.core.evaluation.datasets import load_dataset, split  # noqa: E402
from vloc.workers.core.features import DESCRIPTOR_NAMES, DESCRIPTORS, extract_many  # noqa: E402
from vloc.workers.core.features.descriptors import (  # noqa: E402
    describe,
    local_vectors,
    train_descriptor_vocabulary,
)
from vloc.workers.core.features.orb import extract_orb  # noqa: E402
from vloc.workers.core.image import decode_image, prepare  # noqa: E402
from vloc.workers.core.measures import descriptor_similarities, weiss_similarity  # noqa: E402
from vloc.workers.core.query import QueryFrame  # noqa: E402
from vloc.workers.core.sift import extract_sift  # noqa: E402

SENECA = DATASETS / "seneca-uav"


def _views(images: list[np.ndarray], n: int, rng: np.random.Generator) -> list:
    """``n`` 320x240 frames cut from the photographs at random centres, headings, scales."""
    frames = []
    for i in range(n):
        img = images[i % len(images)]
        h, w = img.shape[:2]
        centre = (float(rng.uniform(0.35, 0.65) * w), float(rng.uniform(0.35, 0.65) * h))
        m = cv2.getRotationMatrix2D(centre, float(rng.uniform(0, 360)),
                                    float(rng.uniform(0.9, 1.4)))
        m[:, 2] += np.array([w / 2, h / 2]) - np.array(centre)
        frames.append(prepare(cv2.warpAffine(img, m, (w, h), borderMode=cv2.BORDER_REFLECT)))
    return frames


def _median(values) -> float:
    return float(np.median(np.asarray(values)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--map-images", type=int, default=1000)
    ap.add_argument("--queries", type=int, default=40)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=RESULTS / "place_timing.md")
    args = ap.parse_args()
    if not (SENECA / "images").is_dir():
        sys.exit(f"data set not found: {SENECA}")
    rng = np.random.default_rng(args.seed)
    ds = load_dataset(SENECA)
    map_imgs, query_imgs = split(ds, "pass", map_pass=1, query_pass=2)
    photos = [decode_image(im.path.read_bytes()) for im in ds.images]
    frames = _views(photos, args.map_images, rng)
    print(f"{len(frames)} map views; extracting ORB and SIFT", flush=True)
    orb = [extract_orb(f.grey) for f in frames]
    sift = [extract_sift(f.grey) for f in frames]
    hist = [extract_many(("wgoh", "wgii"), f) for f in frames]
    queries = [prepare(decode_image(im.path.read_bytes()))
               for im in query_imgs[: args.queries]]

    rows = []
    for name in DESCRIPTOR_NAMES:
        spec = DESCRIPTORS[name]
        per_image = [local_vectors(spec.local, orb=o, sift=s) for o, s in zip(orb, sift,
                                                                              strict=True)]
        train_s, encode_s = [], []
        for r in range(args.repeats):
            t0 = time.thread_time()
            vocab = train_descriptor_vocabulary(spec, per_image, rng=np.random.default_rng(r))
            t1 = time.thread_time()
            matrix = np.stack([describe(spec, v, vocab) for v in per_image])
            t2 = time.thread_time()
            train_s.append(t1 - t0)
            encode_s.append(t2 - t1)
        vocabularies = {name: vocab}
        local_ms, enc_ms, score_ms, total_ms, wall_ms = [], [], [], [], []
        for _ in range(args.repeats):
            for f in queries:
                q = QueryFrame(f)  # fresh: nothing cached
                w0, t0 = time.perf_counter(), time.thread_time()
                if spec.local == "orb":
                    q.orb()
                else:
                    q.sift()
                t1 = time.thread_time()
                vec = q.global_features((name,), vocabularies)[0][name]
                t2 = time.thread_time()
                descriptor_similarities(vec, matrix)
                t3, w3 = time.thread_time(), time.perf_counter()
                local_ms.append((t1 - t0) * 1e3)
                enc_ms.append((t2 - t1) * 1e3)
                score_ms.append((t3 - t2) * 1e3)
                total_ms.append((t3 - t0) * 1e3)
                wall_ms.append((w3 - w0) * 1e3)
        rows.append((name, spec.dim, _median(local_ms), _median(enc_ms), _median(score_ms),
                     _median(total_ms), _median(wall_ms),
                     _median(np.subtract(total_ms, local_ms)) if spec.local == "rootsift"
                     else None, _median(train_s), _median(encode_s)))
        print(f"{name}: done", flush=True)

    m_wgoh = np.stack([h["wgoh"] for h in hist])
    m_wgii = np.stack([h["wgii"] for h in hist])
    ext_ms, score_ms, total_ms, wall_ms = [], [], [], []
    for _ in range(args.repeats):
        for f in queries:
            w0, t0 = time.perf_counter(), time.thread_time()
            g = extract_many(("wgoh", "wgii"), f)
            t1 = time.thread_time()
            weiss_similarity(g["wgoh"], m_wgoh, g["wgii"], m_wgii)
            t2, w2 = time.thread_time(), time.perf_counter()
            ext_ms.append((t1 - t0) * 1e3)
            score_ms.append((t2 - t1) * 1e3)
            total_ms.append((t2 - t0) * 1e3)
            wall_ms.append((w2 - w0) * 1e3)

    n = f"{args.map_images:,}"
    lines = ["# Place descriptors: global step and vocabulary training, one core", "",
             f"{platform.machine()}, {platform.processor() or 'cpu'}, Python "
             f"{platform.python_version()}, OpenCV {cv2.__version__}, numpy {np.__version__}; "
             f"one thread, one CPU. Map: {args.map_images} views of seneca-uav; queries: "
             f"{len(queries)} frames of pass 2, {args.repeats} runs each; medians. Load "
             f"average of the machine at the end: {os.getloadavg()[0]:.1f} on "
             f"{os.cpu_count()} CPUs (shared).",
             "Command: `.venv/bin/python bench/bench_place.py`.", "",
             f"| feature | dim | local features (ms) | describe (ms) | score {n} images (ms) "
             f"| global step (ms) | wall clock (ms) | without SIFT extraction (ms) | vocabulary "
             f"training on {n} images (s) | describing {n} map images (s) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for name, dim, loc, enc, sc, tot, wall, no_sift, tr, en in rows:
        ns = "-" if no_sift is None else f"{no_sift:.1f}"
        lines.append(f"| {name} | {dim} | {loc:.1f} | {enc:.2f} | {sc:.2f} | {tot:.1f} | "
                     f"{wall:.1f} | {ns} | {tr:.2f} | {en:.2f} |")
    lines.append(f"| wgoh x wgii | 256 | {_median(ext_ms):.1f} | - | {_median(score_ms):.2f} | "
                 f"{_median(total_ms):.1f} | {_median(wall_ms):.1f} | - | - | - |")
    lines += ["", "Global step = extracting the frame's local features + describing it + "
              "scoring every map image; the filter's own work (300 particles) comes on top "
              "(`bench/results/core.md`). For RootSIFT the last time column leaves out the "
              "SIFT extraction, which a SIFT step has already paid when the descriptor "
              "shortlists its candidates.", ""]
    write_result(args.out, "\n".join(lines))


if __name__ == "__main__":
    main()
