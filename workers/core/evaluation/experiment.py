"""From a dataset folder to what :mod:`.evaluate` needs: a map, query frames, the truth.

Map images are positioned by what the images themselves say (EXIF GPS; CSV where the image
has none). Query truth is the CSV's position where there is one (the ground truth), else the
image's own tag.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..image import prepare
from ..mapbuild import assemble_map, extract_image_features, typical_focal_px
from ..mapdata import MapData
from ..metadata import FrameMetadata
from ..query import QueryFrame
from ..tiepoints import extract_tie_points
from .datasets import Dataset, DatasetImage, load_dataset, load_frames, split


@dataclass
class Experiment:
    dataset: Dataset
    map_images: list[DatasetImage]
    query_images: list[DatasetImage]
    map_data: MapData
    queries: list[QueryFrame]
    truth: np.ndarray  # (n, 2) east/north of the query frames in the map frame
    photometric: str
    geometry: dict = field(default_factory=dict)
    """What became of the map's camera geometry (:func:`.mapbuild.geometry_report`)."""


def _timestamp(img: DatasetImage) -> float | None:
    return None if img.captured_at is None else img.captured_at.timestamp()


def build_map(images: list[DatasetImage], frames, *, map_id: str = "",
              report: dict | None = None, geometry: bool = True, seed: int = 0,
              kept: str | Path | None = None, previous: MapData | None = None,
              revision: int = 0,
              timings: dict[str, tuple[float, float]] | None = None) -> MapData:
    """Extract every feature of the map images and pack the map (without camera geometry
    where ``geometry`` is false) with the build's ``seed``; ``report`` is filled with what
    became of its geometry, ``timings`` with its stages' (wall, CPU) seconds. With a
    folder ``kept``, the build registers the images into the COLMAP models an earlier build
    of some of them kept there, and keeps its own (:mod:`..geometry.kept`; images are named
    by their file names); with ``previous``, the map an earlier build packed of some of
    them, it carries over what still holds of it and keeps its local frame, as the
    service's updates do (:mod:`..carryover`; images named by their file names too)."""
    from ..carryover import Previous
    from ..geometry.kept import KeptModels

    feats = [replace(extract_image_features(f),
                     tie=extract_tie_points(im.path.read_bytes()) if geometry else None)
             for im, f in zip(images, frames, strict=True)]
    focal = typical_focal_px([im.path.read_bytes for im in images])
    return assemble_map(names=[im.name for im in images], lats=[im.lat for im in images],
                        lons=[im.lon for im in images], alts=[im.alt for im in images],
                        features=feats, captured_at=[_timestamp(im) for im in images],
                        map_id=map_id, revision=revision, focal_px=focal, report=report,
                        origin=None if previous is None else previous.origin,
                        geometry=geometry, seed=seed, timings=timings,
                        kept=None if kept is None else KeptModels(
                            Path(kept), tuple(im.name for im in images)),
                        previous=None if previous is None else Previous.of(
                            previous, previous.names, [im.name for im in images]))


def truth_positions(images: list[DatasetImage], map_data: MapData) -> np.ndarray:
    lat = [im.truth_lat if im.truth_lat is not None else im.lat for im in images]
    lon = [im.truth_lon if im.truth_lon is not None else im.lon for im in images]
    e, n = map_data.origin.to_local(lat, lon)
    return np.column_stack([np.atleast_1d(e), np.atleast_1d(n)])


def load_experiment(folder: str | Path, *, rule: str = "pass",
                    map_pass: int | tuple[int, ...] | None = None,
                    query_pass: int | None = None, photometric: str = "none",
                    seed: int = 0, geometry: bool = True, build_seed: int = 0) -> Experiment:
    """Load, split, build the map and prepare the (possibly relit) query frames; the map
    without camera geometry where ``geometry`` is false (a configuration that does not
    refine, such as the papers' own, has no use for it). ``seed`` draws the relighting,
    ``build_seed`` seeds the map's build (its RANSACs, COLMAP, its vocabularies): another
    build seed shows how much of a change in the errors the build's chance alone makes."""
    from .photometric import apply_variant, variant_rng

    ds = load_dataset(folder)
    map_images, query_images = split(ds, rule, map_pass=map_pass, query_pass=query_pass)
    report: dict = {}
    map_data = build_map(map_images, load_frames(map_images), map_id=ds.folder.name,
                         report=report, geometry=geometry, seed=build_seed)
    frames = load_frames(query_images)
    if photometric != "none":
        frames = [prepare(apply_variant(f.colour, photometric, rng=variant_rng(seed, i)))
                  for i, f in enumerate(frames)]
    queries = [QueryFrame(f, _timestamp(im), key=i)
               for i, (f, im) in enumerate(zip(frames, query_images, strict=True))]
    return Experiment(ds, map_images, query_images, map_data, queries,
                      truth_positions(query_images, map_data), photometric, report)


def frame_metadata(exp: Experiment, kinds: tuple[str, ...], *, gps_accuracy: float | None = None,
                   heading_sigma: float = 5.0, seed: int = 0) -> list[FrameMetadata | None]:
    """Per query frame, the device metadata of the named kinds, for ``--use-metadata``.

    Each kind comes from the data set's CSV columns where it has them. Where it has not
    (seneca-uav records only the GPS it is evaluated against), it is simulated from the
    truth, seeded:

    - ``gps``: a fix of horizontal accuracy ``gps_accuracy`` (metres, one standard deviation
      per axis): the true position plus Gaussian noise of that size. Needs ``gps_accuracy``.
    - ``heading``: a compass of ``heading_sigma`` degrees: the camera heading that SIFT
      registration against the map's geometry gives where that solve lies within 10 m of
      the true position (the only heading truth a nadir data set has), plus noise; frames
      without such a solve carry no heading.
    - ``velocity``: the true track's velocity between neighbouring frames (with times)
      plus noise of 10 % of the speed.
    - ``altitude``: the image's own altitude tag.
    """
    from ..localisers.refine import refine_sift
    from ..metadata import METADATA_KINDS

    unknown = set(kinds) - set(METADATA_KINDS)
    if unknown:
        raise ValueError(f"unknown metadata kinds {sorted(unknown)}; valid: "
                         f"{', '.join(METADATA_KINDS)}")
    rng = np.random.default_rng(seed)
    md = exp.map_data
    truth = exp.truth
    times = np.array([np.nan if q.captured_at is None else q.captured_at for q in exp.queries])
    out: list[FrameMetadata | None] = []
    for i, (img, q) in enumerate(zip(exp.query_images, exp.queries, strict=True)):
        given = img.metadata.only(kinds) if img.metadata is not None else FrameMetadata()
        fields = given.to_dict()
        if "gps" in kinds and not given.has_gps:
            if gps_accuracy is None:
                raise ValueError("the data set has no GPS columns: give a GPS accuracy to "
                                 "simulate a fix from the truth")
            xy = truth[i] + rng.normal(0.0, gps_accuracy, size=2)
            lat, lon = md.origin.to_wgs84(xy[0], xy[1])
            fields.update(gps_lat=float(lat), gps_lon=float(lon), gps_accuracy_m=gps_accuracy)
        if "heading" in kinds and not given.has_heading and md.geometry is not None:
            near = np.argsort(np.linalg.norm(np.asarray(md.positions) - truth[i], axis=1))[:3]
            fix = refine_sift(q.sift()[0], md, near, np.ones(len(near)),
                              frame_shape=q.frame.grey.shape)
            if (fix is not None and fix.heading_deg is not None
                    and np.linalg.norm(fix.xy - truth[i]) <= 10.0):
                fields.update(heading_deg=float((fix.heading_deg + rng.normal(0.0, heading_sigma))
                                                % 360.0),
                              heading_accuracy_deg=heading_sigma)
        if "velocity" in kinds and not given.has_velocity and len(truth) > 1:
            a, b = max(i - 1, 0), min(i + 1, len(truth) - 1)
            dt = times[b] - times[a]
            if np.isfinite(dt) and dt > 0:
                v = (truth[b] - truth[a]) / dt
                v = v + rng.normal(0.0, 0.1 * float(np.hypot(*v)) + 1e-3, size=2)
                fields.update(velocity_east=float(v[0]), velocity_north=float(v[1]))
        if "altitude" in kinds and given.altitude_m is None and img.alt is not None:
            fields.update(altitude_m=float(np.clip(img.alt, -500.0, 10_000.0)))
        out.append(FrameMetadata(**fields) if fields else None)
    return out
