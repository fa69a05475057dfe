"""Replay the large-map benchmark's session on a map packed directly, in minutes.

``bench_large_map.py`` builds its map through the service, and the camera geometry alone
takes more than an hour at 50,000 images on two cores, so it is no way to try a change to
localisation on a large map. This script takes the same world (the tiles of
:mod:`large_map_world`'s 50,000-image layout, generated where missing), extracts each
tile's map features as the build does (:func:`~workers.core.mapbuild.extract_image_features`,
cached per tile in the work directory), packs the first ``--images`` of them with the core
(:func:`~workers.core.mapbuild.assemble_map`, shortlist codes above 8,192 images, *no camera
geometry*: global steps do not register with ORB and SIFT steps place the frame between
its best images) and runs the benchmark's session over the query pass from the same
initial pose (:func:`bench_large_map.time_steps`). It prints the error, the share of SIFT
steps, the step times and the map's typical speed.

Usage::

    .venv/bin/python bench/large_map_replay.py WORK [--images 12000] [--frames 200]
        [--jobs 2] [--param KEY=VALUE ...]

``--param`` changes the ``default`` configuration (flat keys, values as JSON), e.g.
``--param speed=6.7``.
"""

from __future__ import annotations

from _common import one_thread, repo_on_path

one_thread()

import argparse  # noqa: E402
import json  # noqa: E402
import pickle  # noqa: E402
import time  # noqa: E402
from concurrent.futures import ProcessPoolExecutor  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

repo_on_path()

from bench_large_map import query_frames, time_steps  # noqa: E402
from large_map_world import generate_tile, layout_for, tile_dir, tile_done  # noqa: E402


def tile_features(work: Path, tile: int) -> Path:
    """Generate tile ``tile`` where missing and extract its map images' features once;
    returns the file holding (name, lat, lon, alt, captured_at) rows and the features."""
    import cv2

    from vloc.workers.core.evaluation.datasets import load_dataset, load_frames
    from vloc.workers.core.mapbuild import extract_image_features

    cv2.setNumThreads(1)
    out = work / "replay" / "features" / f"tile_{tile:03d}.pkl"
    if out.is_file():
        return out
    if not tile_done(work, tile):
        generate_tile(work, layout_for(50_000), tile)
    images = [im for im in load_dataset(tile_dir(work, tile)).images if im.pass_ == 1]
    features = [extract_image_features(f) for f in load_frames(images)]
    rows = [(im.name, im.lat, im.lon, im.alt,
             None if im.captured_at is None else im.captured_at.timestamp()) for im in images]
    out.parent.mkdir(parents=True, exist_ok=True)
    partial = out.with_suffix(".partial")
    with partial.open("wb") as f:
        pickle.dump((rows, features), f, protocol=pickle.HIGHEST_PROTOCOL)
    partial.replace(out)
    return out


def packed_map(work: Path, images: int, jobs: int) -> Path:
    """The folder of the map of the first ``images`` map frames, packed once."""
    from vloc.workers.core.mapbuild import assemble_map

    folder = work / "replay" / f"map_{images}"
    if (folder / "meta.json").is_file():
        return folder
    tiles = layout_for(images).tiles
    with ProcessPoolExecutor(jobs) as pool:
        files = list(pool.map(tile_features, [work] * tiles, range(tiles)))
    rows, features = [], []
    for path in files:
        with path.open("rb") as f:
            r, feats = pickle.load(f)
        rows += r
        features += feats
    rows, features = rows[:images], features[:images]
    t0 = time.perf_counter()
    data = assemble_map(names=[r[0] for r in rows], lats=[r[1] for r in rows],
                        lons=[r[2] for r in rows], alts=[r[3] for r in rows],
                        captured_at=[r[4] for r in rows], features=features, geometry=False)
    data.save(folder)
    print(f"packed {images} images in {time.perf_counter() - t0:.0f} s", flush=True)
    return folder


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("work", type=Path, help="work directory (the world goes in world/)")
    parser.add_argument("--images", type=int, default=12_000)
    parser.add_argument("--frames", type=int, default=200, help="query frames to step")
    parser.add_argument("--jobs", type=int, default=2, help="processes extracting features")
    parser.add_argument("--param", action="append", default=[], metavar="KEY=VALUE",
                        help="change the default configuration (value as JSON)")
    args = parser.parse_args()
    params = {}
    for item in args.param:
        key, _, value = item.partition("=")
        params[key] = json.loads(value)
    folder = packed_map(args.work, args.images, args.jobs)
    from vloc.workers.core.mapdata import MapData

    data = MapData.load(folder)
    speed = data.typical_speed()
    frames = query_frames(args.work, args.frames)
    out = time_steps(str(folder), frames, params)
    errors = np.asarray(out["errors"])
    sift_share = np.mean([kind == "sift" for kind, _ in out["frame_ms"]])
    global_ms = [1e3 * s for kind, s in out["steps"] if kind == "global"]
    far = np.flatnonzero(errors > 30.0)
    print(f"map {len(data)} images, typical speed {speed:.1f} m/s, params {params or '-'}")
    print(f"{len(errors)} frames: median error {np.median(errors):.1f} m, "
          f"90th percentile {np.percentile(errors, 90):.1f} m, SIFT on {sift_share:.0%} "
          f"of the steps, first frame over 30 m: {far[0] if len(far) else '-'}")
    if global_ms:
        print(f"global step median {np.median(global_ms):.1f} ms (CPU, one core, "
              f"{len(global_ms)} steps; no ORB registration on a map without geometry)")


if __name__ == "__main__":
    main()
