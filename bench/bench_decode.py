"""Benchmark: what decoding a frame costs in a worker, part by part, on one core.

A worker turns a frame's bytes into the working-resolution image with
:func:`workers.core.image.load_frame`: the header read (skipped where the API process read
it; with the size, the EXIF orientation, which OpenCV applies), one strict decode at the reduced scale the working size
allows (simplejpeg: a file cut short is refused rather than filled with grey), and the
resize. Beside it, the two reads a JPEG took before (the strict completeness check at 1/8
scale, then OpenCV's decode), which give the same pixels. Each part is timed side by side on
the same frames, in one run: medians of repeated runs per frame, then the median over the
frames.

Usage::

    .venv/bin/python bench/bench_decode.py [--images FOLDER] [--frames 20] [--repeats 15]
                                           [--out bench/results/decode.md]

By default the frames are seneca-uav's (``../shared/datasets/seneca-uav/images``).
"""

from __future__ import annotations

from _common import DATASETS, one_thread, repo_on_path, write_result

one_thread()

import argparse  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

repo_on_path()

from vloc.workers.core import image  # noqa: E402

cv2.setNumThreads(1)


def _median_ms(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e3)


def measure(data: bytes, repeats: int) -> dict[str, float]:
    """Milliseconds of each part of one frame's decode, of the whole, and of the two reads
    it took before."""
    import simplejpeg

    header = image.read_header(data)
    size = (header.width, header.height)
    flag, scale = cv2.IMREAD_COLOR, 1
    for factor, reduced in image._REDUCED:
        if size[0] // factor >= image.WORK_SIZE[0] and size[1] // factor >= image.WORK_SIZE[1]:
            flag, scale = reduced, factor
            break
    buf = np.frombuffer(data, np.uint8)
    decoded = cv2.imdecode(buf, flag)

    def completeness_check():
        """The strict pass a JPEG took before OpenCV's decode: every block at 1/8 scale."""
        return simplejpeg.decode_jpeg(data, colorspace="GRAY", strict=True, min_height=1,
                                      min_width=1)

    def before():
        completeness_check()
        return image.prepare(cv2.imdecode(buf, flag))

    assert np.array_equal(before().grey, image.load_frame(data).grey)
    return {
        "header (size, EXIF orientation)": _median_ms(lambda: image.read_header(data),
                                                      repeats),
        "strict decode (simplejpeg)": _median_ms(lambda: simplejpeg.decode_jpeg(
            data, colorspace="BGR", strict=True, min_width=-(-size[0] // scale),
            min_height=-(-size[1] // scale)), repeats),
        "resize": _median_ms(lambda: image.prepare(decoded), repeats),
        "load_frame": _median_ms(lambda: image.load_frame(data), repeats),
        "load_frame, header given": _median_ms(
            lambda: image.load_frame(data, header=header), repeats),
        "before: completeness check": _median_ms(completeness_check, repeats),
        "before: OpenCV decode": _median_ms(lambda: cv2.imdecode(buf, flag), repeats),
        "before: check, OpenCV decode, resize (header given)": _median_ms(before, repeats),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--images", type=Path, default=DATASETS / "seneca-uav" / "images")
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    paths = sorted(p for p in args.images.iterdir()
                   if p.suffix.lower() in (".jpg", ".jpeg"))[:args.frames]
    if not paths:
        raise SystemExit(f"no JPEG frames in {args.images}")
    rows = [measure(p.read_bytes(), args.repeats) for p in paths]
    size = image.read_header(paths[0].read_bytes())
    whole = np.median([r["load_frame"] for r in rows])
    name = args.images.parent.name if args.images.name == "images" else args.images.name
    lines = ["# Decoding a frame in a worker", "",
             f"`python bench/bench_decode.py` on {len(paths)} frames of {name} "
             f"({size[0]}x{size[1]} JPEG), one core; medians of {args.repeats} runs per frame, "
             "then over the frames.", "",
             "| part | ms | share of load_frame |", "|---|---|---|"]
    for part in rows[0]:
        ms = float(np.median([r[part] for r in rows]))
        lines.append(f"| {part} | {ms:.2f} | {ms / whole:.0%} |")
    before = np.median([r["before: check, OpenCV decode, resize (header given)"]
                        for r in rows])
    given = np.median([r["load_frame, header given"] for r in rows])
    lines += ["", f"One strict decode against the two reads before (header given, same run): "
                  f"{given:.2f} ms against {before:.2f} ms, {before / given:.2f}x."]
    text = "\n".join(lines)
    print(text)
    if args.out is not None:
        write_result(args.out, text + "\n", echo=False)


if __name__ == "__main__":
    main()
