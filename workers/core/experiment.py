"""From a dataset folder to what :mod:`.evaluate` needs: a map, query frames, the truth.

Map images are positioned by what the images themselves say (EXIF GPS; CSV where the image
has none). Query truth is the CSV's position where there is one (the ground truth), else the
image's own tag.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .datasets import Dataset, DatasetImage, load_dataset, load_frames, split
from .image import prepare
from .mapbuild import assemble_map, extract_image_features, typical_focal_px
from .mapdata import MapData
from .query import QueryFrame


@dataclass
class Experiment:
    dataset: Dataset
    map_images: list[DatasetImage]
    query_images: list[DatasetImage]
    map_data: MapData
    queries: list[QueryFrame]
    truth: np.ndarray  # (n, 2) east/north of the query frames in the map frame
    photometric: str


def _timestamp(img: DatasetImage) -> float | None:
    return None if img.captured_at is None else img.captured_at.timestamp()


def build_map(images: list[DatasetImage], frames, *, map_id: str = "") -> MapData:
    """Extract every feature of the map images and pack the map."""
    feats = [extract_image_features(f) for f in frames]
    focal = typical_focal_px([im.path.read_bytes for im in images])
    return assemble_map(names=[im.name for im in images], lats=[im.lat for im in images],
                        lons=[im.lon for im in images], alts=[im.alt for im in images],
                        features=feats, captured_at=[_timestamp(im) for im in images],
                        map_id=map_id, focal_px=focal)


def truth_positions(images: list[DatasetImage], map_data: MapData) -> np.ndarray:
    lat = [im.truth_lat if im.truth_lat is not None else im.lat for im in images]
    lon = [im.truth_lon if im.truth_lon is not None else im.lon for im in images]
    e, n = map_data.origin.to_local(lat, lon)
    return np.column_stack([np.atleast_1d(e), np.atleast_1d(n)])


def load_experiment(folder: str | Path, *, rule: str = "pass", map_pass: int | None = None,
                    query_pass: int | None = None, photometric: str = "none",
                    seed: int = 0) -> Experiment:
    """Load, split, build the map and prepare the (possibly relit) query frames."""
    from .photometric import apply_variant, variant_rng

    ds = load_dataset(folder)
    map_images, query_images = split(ds, rule, map_pass=map_pass, query_pass=query_pass)
    map_data = build_map(map_images, load_frames(map_images), map_id=ds.folder.name)
    frames = load_frames(query_images)
    if photometric != "none":
        frames = [prepare(apply_variant(f.colour, photometric, rng=variant_rng(seed, i)))
                  for i, f in enumerate(frames)]
    queries = [QueryFrame(f, _timestamp(im), key=i)
               for i, (f, im) in enumerate(zip(frames, query_images, strict=True))]
    return Experiment(ds, map_images, query_images, map_data, queries,
                      truth_positions(query_images, map_data), photometric)
