"""Benchmark: decode, prepare, every global feature and every measure, on one core.

Times are medians over repeated runs of one 320x240 frame (the working resolution) and, for
the measures, of one query against a 400-row map matrix (the size of the design's reference
map). Threads are pinned to one before numpy and OpenCV load, so the figures are per core.

Usage::

    .venv/bin/python bench/bench_features.py [--repeats 200] [--image PATH] [--out PATH]

Writes a Markdown table (default ``bench/results/features.md``) and prints it.
"""

from __future__ import annotations

from _common import RESULTS, ROOT, one_thread, repo_on_path, write_result

one_thread()

import argparse  # noqa: E402
import platform  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

repo_on_path()

from vloc.workers.core.features import FEATURE_NAMES, GLOBAL_FEATURES, extract_many  # noqa: E402
from vloc.workers.core.image import decode_image, prepare  # noqa: E402
from vloc.workers.core.measures import (  # noqa: E402
    MEASURES,
    normalise,
    similarities,
    weiss_similarity,
)

DEFAULT_IMAGE = ROOT / ".." / "shared" / "datasets" / "seneca-uav" / "images" / "IMG_0446.jpg"
MAP_ROWS = 400


def _median_ms(fn, repeats: int) -> float:
    fn()  # warm caches and lazily built tables
    times = np.empty(repeats)
    for i in range(repeats):
        t0 = time.perf_counter()
        fn()
        times[i] = time.perf_counter() - t0
    return float(np.median(times) * 1e3)


def _generated_jpeg(rng: np.random.Generator) -> bytes:
    """A textured 1280x960 colour JPEG, for when the real image is absent."""
    noise = rng.normal(0, 1, (960, 1280, 3)).astype(np.float32)
    image = cv2.GaussianBlur(noise, (0, 0), 6)
    image = np.clip(128 + 60 * image / image.std(), 0, 255).astype(np.uint8)
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 90])
    assert ok
    return buf.tobytes()


def run(image_path: Path, repeats: int) -> tuple[list[tuple[str, str, float]], str]:
    cv2.setNumThreads(1)
    rng = np.random.default_rng(0)
    if image_path.is_file():
        data, source = image_path.read_bytes(), image_path.name
    else:
        data, source = _generated_jpeg(rng), "generated 1280x960 JPEG"
    image = decode_image(data)
    source += f" ({image.shape[1]}x{image.shape[0]})"
    frame = prepare(image)

    rows: list[tuple[str, str, float]] = [
        ("image", "decode JPEG", _median_ms(lambda: decode_image(data), repeats)),
        ("image", "prepare (resize to 320x240, grey)", _median_ms(lambda: prepare(image),
                                                                  repeats)),
    ]
    for name in FEATURE_NAMES:
        spec = GLOBAL_FEATURES[name]
        rows.append(("feature", f"`{name}` ({spec.dim}-d)",
                     _median_ms(lambda spec=spec: spec.fn(frame), repeats)))
    rows.append(("feature", "`extract_many` of all six",
                 _median_ms(lambda: extract_many(FEATURE_NAMES, frame), repeats)))
    rows.append(("feature", "`extract_many` wgoh + wgii (Weiss)",
                 _median_ms(lambda: extract_many(("wgoh", "wgii"), frame), repeats)))

    # a map of perturbed copies of real features, so the values are realistic
    query = extract_many(FEATURE_NAMES, frame)
    for measure in MEASURES:
        q = query["wgoh"]
        M = (q[None, :] * rng.uniform(0.5, 1.5, (MAP_ROWS, q.size))).astype(np.float32)
        rows.append(("measure", f"`{measure}`, 128-d, {MAP_ROWS} rows",
                     _median_ms(lambda m=measure, q=q, M=M: similarities(m, q, M), repeats)))
        qn, Mn = normalise(q, measure), normalise(M, measure)
        rows.append(("measure", f"`{measure}`, pre-normalised map",
                     _median_ms(lambda m=measure, q=qn, M=Mn:
                                similarities(m, q, M, normalised=True), repeats)))
    qo, qi = query["wgoh"], query["wgii"]
    Mo = (qo[None, :] * rng.uniform(0.5, 1.5, (MAP_ROWS, 128))).astype(np.float32)
    Mi = (qi[None, :] * rng.uniform(0.5, 1.5, (MAP_ROWS, 128))).astype(np.float32)
    rows.append(("measure", f"`weiss_similarity` (WGOH x WGII), {MAP_ROWS} rows",
                 _median_ms(lambda: weiss_similarity(qo, Mo, qi, Mi), repeats)))
    return rows, source


def render(rows, source: str, repeats: int) -> str:
    lines = [
        "# Global features and similarity measures: time per call",
        "",
        f"Median of {repeats} runs, one thread (`cv2.setNumThreads(1)`, OMP/OpenBLAS/MKL "
        "threads 1), one 320x240 frame; measures compare one query with a "
        f"{MAP_ROWS}-row map matrix. Image: {source}.",
        "",
        f"Machine: {platform.processor() or platform.machine()}, Python "
        f"{platform.python_version()}, numpy {np.__version__}, OpenCV {cv2.__version__}.",
        "Measured with `.venv/bin/python bench/bench_features.py`.",
        "",
        "| stage | what | median ms |",
        "|---|---|---:|",
    ]
    lines += [f"| {stage} | {what} | {ms:.3f} |" for stage, what, ms in rows]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=200)
    parser.add_argument("--image", type=Path, default=DEFAULT_IMAGE)
    parser.add_argument("--out", type=Path, default=RESULTS / "features.md")
    args = parser.parse_args(argv)
    rows, source = run(args.image, args.repeats)
    text = render(rows, source, args.repeats)
    write_result(args.out, text)


if __name__ == "__main__":
    main()
