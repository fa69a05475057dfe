"""A packed revision read from chunks against the same revision in one file per array.

Revisions store their rows per image in chunks that later revisions share on disk
(:mod:`vloc.workers.core.rowchunks`); a localiser then reads an image's keypoints, a frame's
matched 3-D points and the place descriptors through :class:`ChunkedRows` instead of one
memory-mapped array. This measures what that costs a session: the revision given, and a copy
of it written the way revisions were before chunks (each array whole), both memory-mapped,
each localise the same query frames with a ``default`` hybrid filter from the same initial
pose, the two alternately, repeat after repeat, CPU time of each step on one thread. Reported:
median CPU ms per frame of each, their ratio, and how far the two runs' estimates lie apart
(the place descriptors' product with a frame's, taken chunk by chunk, can differ from the
whole matrix's in its last bits).

    python bench/bench_map_chunks.py --revision PATH --dataset PATH [--frames 100]
                                     [--repeats 3] [--out bench/results/map_chunks.md]

``--revision`` is a packed revision folder (``data/maps/<map>/rev-<n>``, the 1,000-image
benchmark map's, say); ``--dataset`` the folder of its images, whose second pass gives the
frames.
"""

from __future__ import annotations

from _common import RESULTS, machine_and_python, one_thread, repo_on_path, write_result

one_thread()

import argparse  # noqa: E402
import json  # noqa: E402
import shutil  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

repo_on_path()

from vloc.workers.core.evaluation.datasets import load_dataset, split  # noqa: E402
from vloc.workers.core.image import load_frame  # noqa: E402
from vloc.workers.core.localisers import make_localiser  # noqa: E402
from vloc.workers.core.mapdata import MapData  # noqa: E402
from vloc.workers.core.query import QueryFrame  # noqa: E402


def whole_copy(revision: Path, out: Path) -> Path:
    """``revision`` rewritten with each chunked array in one file, as before chunks."""
    shutil.copytree(revision, out)
    for meta_file, key in (("meta.json", "chunks"), ("geometry.json", "point_chunks")):
        path = out / meta_file
        if not path.exists():
            continue
        meta = json.loads(path.read_text())
        for stem, chunks in meta.pop(key, {}).items():
            name = stem if key == "chunks" else f"geometry_points_{stem}"
            np.save(out / f"{name}.npy", np.concatenate([np.load(out / n) for n, _ in chunks]))
            for n, _ in chunks:
                (out / n).unlink(missing_ok=True)
        path.write_text(json.dumps(meta))
    return out


def run(data: MapData, frames: list[QueryFrame], start: tuple[float, float],
        ) -> tuple[list[float], np.ndarray]:
    loc = make_localiser("hybrid", data, {"config": "default"}, seed=0)
    loc.set_initial_pose(*start, 10.0)
    cpu, xy = [], []
    for q in frames:
        fresh = QueryFrame(q.frame, q.captured_at, key=q.key)  # nothing cached
        t0 = time.thread_time()
        e = loc.step(fresh)
        cpu.append((time.thread_time() - t0) * 1e3)
        xy.append((e.x, e.y))
    return cpu, np.array(xy)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--revision", type=Path, required=True)
    p.add_argument("--dataset", type=Path, required=True)
    p.add_argument("--frames", type=int, default=100)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--out", type=Path, default=RESULTS / "map_chunks.md")
    args = p.parse_args()
    cv2.setNumThreads(1)
    _, queries = split(load_dataset(args.dataset), "pass", map_pass=1, query_pass=2)
    queries = queries[:args.frames]
    frames = [QueryFrame(load_frame(im.path.read_bytes()),
                         im.captured_at.timestamp() if im.captured_at else None, key=k)
              for k, im in enumerate(queries)]
    with tempfile.TemporaryDirectory() as tmp:
        chunked = MapData.load(args.revision)
        whole = MapData.load(whole_copy(args.revision, Path(tmp) / "whole"))
        start = tuple(float(v) for v in chunked.origin.to_local(queries[0].lat,
                                                                  queries[0].lon))
        meta = json.loads((args.revision / "meta.json").read_text())
        cpu: dict[str, list[float]] = {"chunks": [], "whole": []}
        tracks = {}
        run(whole, frames[:5], start)  # warm the page cache and the code
        for _ in range(args.repeats):
            for label, data in (("whole", whole), ("chunks", chunked)):
                ms, xy = run(data, frames, start)
                cpu[label] += ms
                tracks[label] = xy
    apart = np.hypot(*(tracks["chunks"] - tracks["whole"]).T)
    med = {k: float(np.median(v)) for k, v in cpu.items()}
    n_chunks = len(meta["chunk_images"])
    text = "\n".join([
        "# A revision read from chunks against one file per array", "",
        f"`python bench/bench_map_chunks.py --revision {args.revision.name} --dataset "
        f"{args.dataset.name} --frames {args.frames} --repeats {args.repeats}`", "",
        f"{machine_and_python()}, one thread; "
        f"{len(chunked)} map images in {n_chunks} chunks; {len(frames)} frames of pass 2 "
        f"through a `default` hybrid filter started at the first frame's GPS (sigma 10 m), "
        f"{args.repeats} repeats, the two alternately.", "",
        "| revision read from | median CPU ms per frame | mean |",
        "|---|---|---|",
        *(f"| {k} | {med[k]:.2f} | {np.mean(cpu[k]):.2f} |" for k in ("whole", "chunks")),
        "",
        f"Chunks / whole: {med['chunks'] / med['whole']:.3f}. The two runs' estimates lie "
        f"{np.median(apart):.2g} m apart (median; at most {apart.max():.2g} m).", ""])
    write_result(args.out, text)


if __name__ == "__main__":
    main()
