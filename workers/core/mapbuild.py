"""Building a map: every feature of every map image, then the packed :class:`MapData`.

Extraction is per image and independent (run it in parallel); assembly needs all images at
once, because the SIFT reduction matches each image with its two GPS-nearest neighbours
(Weiss III) and the place descriptors' vocabularies are trained on the local features of
every map image (:mod:`workers.core.features.descriptors`). A first build trains them; an
update keeps them, and what else of the revision before still holds, while they fit the
map's images (:mod:`workers.core.carryover`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from .carryover import Previous, known_masks, known_points
from .features import DESCRIPTOR_NAMES, FEATURE_NAMES, extract_many
from .features.orb import OrbFeatures, extract_orb
from .features.shortlist import CODES_FROM
from .geo import GeoOrigin, local_frame
from .geometry import build_geometry
from .geometry.mapgeometry import structure_digests
from .image import WORK_SIZE, Frame
from .lens import read_focal_px
from .mapdata import MapData
from .mapdescriptors import place_codes, train_descriptors
from .sift import RATIO, SiftFeatures, extract_sift, reduction_masks
from .tiepoints import TiePointFiles
from .timings import Timings, stage


@dataclass(frozen=True, slots=True)
class ImageFeatures:
    """Everything extracted from one map image.

    Attributes
    ----------
    global_features : dict of str -> (D,) float32 ndarray
    sift : SiftFeatures
        All keypoints, before the neighbour reduction.
    orb : OrbFeatures or None
        ORB keypoints for the place descriptors over ORB; None where not extracted.
    tie : SiftFeatures, TiePointFiles or None
        Tie points for the map's reconstruction (:func:`.tiepoints.extract_tie_points`), in
        memory or on disk, used at build time only; None falls back on ``sift``.
    """

    global_features: dict[str, np.ndarray]
    sift: SiftFeatures
    orb: OrbFeatures | None = None
    tie: SiftFeatures | TiePointFiles | None = None


def extract_image_features(frame: Frame, *,
                           features: tuple[str, ...] = FEATURE_NAMES) -> ImageFeatures:
    """Extract the named global features, SIFT and ORB from one map image."""
    return ImageFeatures(extract_many(features, frame), extract_sift(frame.grey),
                         extract_orb(frame.grey))


def assemble_map(*, names, lats, lons, alts, features: list[ImageFeatures],
                 captured_at=None, flights=None, map_id: str = "", revision: int = 0,
                 origin: GeoOrigin | None = None, reduce_sift: bool = True,
                 ratio: float = RATIO, geometry: bool = True,
                 focal_px: float | None = None,
                 descriptors: tuple[str, ...] = DESCRIPTOR_NAMES, seed: int = 0,
                 known_pairs: dict | None = None, known_tiles: dict | None = None,
                 kept=None, previous: Previous | None = None,
                 timings: Timings | None = None,
                 report: dict | None = None,
                 on_stage: Callable[[str], None] | None = None) -> MapData:
    """Pack per-image features into a :class:`MapData`.

    Parameters
    ----------
    names : sequence of str, one per image
    lats, lons : sequence of float (WGS84 degrees)
    alts : sequence of float or None (metres); None entries count as 0
    features : list of ImageFeatures, one per image
    captured_at : sequence of float or None (seconds since the epoch; NaN/None unknown)
    flights : sequence of str or None, optional
        The flight (or pass) each image was said to belong to, None where not said
        (:mod:`workers.core.flights`).
    origin : GeoOrigin or None
        The local frame; by default at the centroid of the images.
    reduce_sift : bool
        Mark the keypoints matching one of the two GPS-nearest map images (Weiss III);
        all keypoints are kept, the mark lets localisers match the reduced set.
    geometry : bool
        Reconstruct the map's cameras and 3-D points (metric refinement,
        :mod:`workers.core.geometry`); maps whose structure cannot be recovered, or does
        not localise their own images better than the nearest image, get none.
    focal_px : float or None
        The map camera's focal length in pixels at the working resolution (from EXIF,
        :func:`workers.core.lens.read_focal_px`); None assumes a typical field of view
        and lets the reconstruction find it.
    descriptors : tuple of str
        Place descriptors to train a vocabulary for and describe every map image with.
        Those over ORB are left out when an image comes without ORB features.
    seed : int
        Seeds the vocabulary training and the reconstruction's RANSAC: the same images
        give the same map.
    known_pairs, known_tiles : dict, optional
        The reconstruction's tie-point pairs matched beforehand with the same ``seed``
        (:mod:`workers.core.tiepairs`), and a large map's tiles reconstructed beforehand
        (:mod:`workers.core.tiles`); the others are matched and reconstructed here.
    kept : KeptModels, optional
        COLMAP's models kept from the map's last build, which images added since are
        registered into (:mod:`workers.core.geometry.kept`).
    previous : Previous, optional
        The map's revision before, whose SIFT reduction masks and place descriptors the
        images it holds keep where they still hold (:mod:`workers.core.carryover`).
    timings : dict, optional
        Filled with (wall, CPU) seconds of each stage: ``"sift reduction"``,
        ``"vocabularies"`` (training and describing every image), ``"packing"``,
        ``"shortlist codes"`` (maps of more than ``CODES_FROM`` images) and ``"geometry"``,
        with its parts (:func:`map_geometry`).
    report : dict, optional
        Filled with what became of the geometry (:func:`geometry_report`).
    on_stage : callable, optional
        Called with ``"geometry"`` as the reconstruction starts (the longest stage of a
        small map's packing).

    Returns
    -------
    MapData
    """
    timings = {} if timings is None else timings
    n = len(names)
    if not (len(lats) == len(lons) == len(alts) == len(features) == n):
        raise ValueError("names, lats, lons, alts and features must have the same length")
    if n == 0:
        raise ValueError("a map needs at least one image")
    origin, xy, alt = local_frame(lats, lons, alts, origin)
    names_in_all = set.intersection(*(set(f.global_features) for f in features))
    glob = {name: np.stack([f.global_features[name] for f in features]).astype(np.float32)
            for name in sorted(names_in_all)}
    sift = [f.sift for f in features]
    with stage(timings, "sift reduction"):
        keep = reduction_masks(sift, xy, ratio=ratio, known=None if previous is None
                               else known_masks(previous)) if reduce_sift else None
    times = None
    if captured_at is not None:
        times = np.array([np.nan if t is None else t for t in captured_at], np.float64)
    with stage(timings, "vocabularies"):
        trained = train_descriptors(features, descriptors, seed=seed, revision=revision,
                                    previous=previous)
    glob.update({name: t.matrix for name, t in trained.items()})
    have_orb = all(f.orb is not None for f in features)
    with stage(timings, "packing"):
        data = MapData.from_parts(origin=origin, names=names, positions=xy, altitudes=alt,
                                  global_features=glob, sift=sift, map_id=map_id,
                                  revision=revision, captured_at=times, flights=flights,
                                  sift_keep=keep,
                                  vocabularies={n: t.vocabulary for n, t in trained.items()},
                                  vocabulary_fits={n: t.fit for n, t in trained.items()},
                                  orb=[f.orb for f in features] if have_orb else None)
    ties = [f.tie for f in features]
    # The map holds its own copies of the features now: let each image's decoded ones go
    # (a large map's would be held twice through the geometry), as long as the caller kept
    # no reference of its own.
    del features, sift, keep
    if n > CODES_FROM:
        # a large map's place descriptors get compact codes for the global steps' scan
        with stage(timings, "shortlist codes"):
            data.place_codes = {name: place_codes(t, previous, seed=seed)
                                for name, t in trained.items()}
    if geometry:
        if on_stage is not None:
            on_stage("geometry")
        with stage(timings, "geometry"):
            data.geometry = map_geometry(data, focal_px=focal_px, seed=seed, tie_points=ties,
                                         known_pairs=known_pairs, known_tiles=known_tiles,
                                         kept=kept, previous=previous, report=report,
                                         timings=timings)
    return data


def map_geometry(data: MapData, *, focal_px: float | None = None, seed: int = 0,
                 tie_points: list[SiftFeatures | TiePointFiles | None] | None = None,
                 known_pairs: dict | None = None, known_tiles: dict | None = None,
                 kept=None, previous: Previous | None = None, report: dict | None = None,
                 timings: Timings | None = None):
    """The map's camera geometry with every stored SIFT (and ORB) keypoint's 3-D point,
    checked by localising the map's own images (:func:`workers.core.selfcheck.self_check`),
    or None.

    ``tie_points`` (one per image, None where missing) tie the images together; an image
    without them is tied by its stored SIFT. ``known_pairs`` and ``known_tiles`` are pairs
    matched and tiles reconstructed beforehand, ``kept`` the models kept from the last build
    (:func:`~workers.core.geometry.build_geometry`). With ``previous`` (the revision an
    update packs from), an image whose structure is that revision's keeps its keypoints'
    3-D points (:func:`~workers.core.carryover.known_points`): a large map's tiles that no
    added image reached are not worked through again. ``report`` is filled with what became
    of the geometry (:func:`geometry_report`). ``timings`` receives the parts' (wall, CPU)
    seconds (:mod:`.timings`): ``"geometry: cameras"`` (the pairs and tiles taken up, what
    is left reconstructed, the models merged), of which ``"geometry: cameras: left-out
    models"``, then ``"geometry: 3-D points"`` and ``"geometry: self-check"``.
    """
    from .selfcheck import self_check

    n = len(data)
    ties = [None] * n if tie_points is None else list(tie_points)
    if len(ties) != n:
        raise ValueError(f"{len(ties)} sets of tie points for {n} map images")
    ties = [data.sift(i) if t is None else t for i, t in enumerate(ties)]
    # read image by image as pairs are matched: tie points on disk stay closed until then
    kps, desc = _Field(ties, "keypoints"), _Field(ties, "descriptors")
    report = {} if report is None else report
    with stage(timings, "geometry: cameras"):
        built = build_geometry(kps, desc, np.asarray(data.positions),
                               np.asarray(data.altitudes), focal_px, seed=seed,
                               known_pairs=known_pairs, known_tiles=known_tiles,
                               times=data.captured_at, flights=data.flights, kept=kept,
                               timings=timings)
    if built is None:
        report.update(status="none", images=n,
                      reason="structure from motion placed too few cameras consistently "
                             "with their GPS")
        return None
    geo, structure = built
    with stage(timings, "geometry: 3-D points"):
        geo.digests = structure_digests(structure)
        seen = _Seen(kps, structure)
        for kind in ("sift", "orb") if data.has_orb else ("sift",):
            keypoints, offsets = map(np.asarray, data.keypoint_set(kind))
            known = None if previous is None else known_points(previous, kind, geo.digests,
                                                               keypoints, offsets)
            geo.add_points(kind, keypoints, offsets, seen, known=known)
    with stage(timings, "geometry: self-check"):
        checked = self_check(data, geo, seed=seed)
    report.update(geometry_report(geo, n))
    if checked is None:
        report["reason"] = ("the map localises its own images no better than their nearest "
                            "map image")
    return checked


def geometry_report(geo, n: int) -> dict:
    """What a map's geometry placed and measured of itself, as plain numbers (JSON): the
    figures the service shows for a revision."""
    check = geo.self_check
    return {"status": "accepted" if check.get("trusted") else "refused", "images": n,
            "placed": int(geo.reconstructed.sum()), "models": int(geo.models),
            "focal_px": float(geo.intrinsics.f), "residual_px": _finite(geo.residual_px),
            "gps_rms_m": _finite(geo.gps_rms), "gps_rms_vertical_m": _finite(geo.gps_rms_v),
            "self_check": {k: (_finite(v) if isinstance(v, float) else v)
                           for k, v in check.items()} if check.get("images") else None}


def _finite(x: float | None) -> float | None:
    return float(x) if x is not None and np.isfinite(x) else None


class _Field(Sequence):
    """One attribute of each of ``items``, read when indexed."""

    def __init__(self, items: list, name: str) -> None:
        self._items, self._name = items, name

    def __len__(self) -> int:
        return len(self._items)

    def __getitem__(self, i: int):
        return getattr(self._items[i], self._name)


class _Seen(Sequence):
    """Each image's reconstructed tie points, (pixels, 3-D points), read when indexed: an
    update reads only the images whose points it works out again."""

    def __init__(self, keypoints: Sequence, structure) -> None:
        self._keypoints, self._structure = keypoints, structure

    def __len__(self) -> int:
        return len(self._keypoints)

    def __getitem__(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        s = self._structure
        if not s.placed[i]:
            return np.zeros((0, 2)), np.zeros((0, 3))
        return np.asarray(self._keypoints[i])[s.observations[i], :2], s.points[i]


def typical_focal_px(files, width: int = WORK_SIZE[0], *, sample: int = 25) -> float | None:
    """Median EXIF focal length (pixels at ``width``) over up to ``sample`` image files.

    Parameters
    ----------
    files : sequence of callables returning bytes, or of bytes
    """
    files = list(files)
    step = max(1, len(files) // sample)
    focals = []
    for f in files[::step]:
        value = read_focal_px(f() if callable(f) else f, width)
        if value is not None:
            focals.append(value)
    return float(np.median(focals)) if focals else None
