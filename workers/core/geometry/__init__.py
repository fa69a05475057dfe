"""Camera geometry: metric positions beyond the nearest map image.

At map build, :func:`build_geometry` reconstructs the map's cameras and the 3-D points they
see with COLMAP (:mod:`.sfm`), on the map's own tie points and verified matches
(:mod:`.pairs`), aligned to the images' GPS (:mod:`.models`, :mod:`.align`), and gives
every stored keypoint its 3-D point (:mod:`.mapgeometry`). Per frame, :func:`register_against` matches the frame's
keypoints to a few map images and solves its camera pose from the 2D-3D matches
(:mod:`.register`). The same path serves nadir, oblique and street-level maps; a map whose
structure cannot be recovered, or whose structure localises its own images no better than
their nearest neighbour (:mod:`workers.core.selfcheck`), gets no geometry, and the
localisers fall back to a match-weighted position between the best verified map images.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from threadpoolctl import threadpool_limits

from ..flights import flight_spacing
from ..image import WORK_SIZE
from ..timings import Timings
from .camera import Intrinsics, focal_from_exif, focal_from_fov
from .kept import KeptModels
from .mapgeometry import MapGeometry
from .models import Structure
from .pairs import PairMatches, candidate_pairs, match_pair, match_pairs
from .register import Registration, register_frame
from .tiling import reconstruct

MIN_PLACED: float = 0.3
"""A reconstruction that places fewer than this share of the map images is not used."""

MAX_RESIDUAL_PX: float = 2.0
"""... nor one whose 3-D points reproject further than this on average (pixels at the
working resolution)."""

MAX_GPS_RMS: float = 15.0
"""... nor one whose cameras sit further than this (m RMS, horizontally) from their GPS."""


REACH_GROWTH: float = 1.5
"""A map's kept tie reach (:func:`tie_pairs`) is decided again once its images call for more
than this many times it: a denser flight added leaves it (each image still takes at most
:data:`TIE_NEIGHBOURS` pairs), a much sparser one would find too few neighbours within it."""

TIE_NEIGHBOURS: int = 12
"""Each map image's tie points are matched with those of at most this many GPS-nearest images
(within :func:`tie_reach`)."""


def tie_reach(positions: np.ndarray, times: np.ndarray | None = None,
              flights=None) -> float:
    """How far apart (m) two map images may be for their tie points to be matched: views
    overlap over a few spacings, and surveys have gaps: six median spacings to the nearest
    image of the same flight (lewis-uav, with gaps of up to 96 m: 23 of 28 images placed, 20
    at 4.5; a second flight over the same waypoints does not shrink it,
    :func:`~workers.core.flights.flight_spacing`, with the flights named in ``flights``)."""
    return max(6.0 * flight_spacing(positions, times, flights), 1.0)


def tie_pairs(positions: np.ndarray, times: np.ndarray | None = None, flights=None, *,
              kept: KeptModels | None = None) -> list[tuple[int, int]]:
    """The pairs of map images whose tie points :func:`build_geometry` matches (``times``:
    capture times, NaN unknown, and ``flights``: the flights named, None where not, which
    tell the map's flights apart): each image with its GPS-nearest within
    :func:`tie_reach`. With ``kept`` (the map's store, :mod:`.kept`), the reach is the one
    kept there (:meth:`.KeptModels.reach`, its first build's), so that images added since
    leave the pairs of the others as they were, unless today's images call for more than
    :data:`REACH_GROWTH` times it (a sparser flight joined the map), which is then kept; a
    first build keeps its own."""
    positions = np.asarray(positions, np.float64)
    if len(positions) < 3:
        return []
    reach = tie_reach(positions, times, flights)
    held = None if kept is None else kept.reach()
    if held is not None and reach <= REACH_GROWTH * held:
        reach = held
    elif kept is not None:
        kept.save_reach(reach)
    return candidate_pairs(positions, max_distance=reach, neighbours=TIE_NEIGHBOURS)


def build_geometry(keypoints: Sequence[np.ndarray], descriptors: Sequence[np.ndarray],
                   positions: np.ndarray, altitudes: np.ndarray, focal_px: float | None, *,
                   seed: int = 0,
                   known_pairs: dict[tuple[int, int], PairMatches | None] | None = None,
                   known_tiles: dict | None = None, times: np.ndarray | None = None,
                   flights=None, kept: KeptModels | None = None,
                   timings: Timings | None = None) -> tuple[MapGeometry, Structure] | None:
    """Reconstruct the map's cameras and 3-D points, or None where that fails.

    Parameters
    ----------
    keypoints, descriptors : sequences, one entry per map image
        Tie points (pixels in the first two keypoint columns; SIFT descriptors), read by
        index as the pairs not in ``known_pairs`` are matched.
    positions : (N, 2) float ndarray
        East/north of the map images (GPS).
    altitudes : (N,) float ndarray
        GPS altitudes, NaN where unknown.
    focal_px : float or None
        The camera's EXIF focal length at the working resolution; None where unknown.
    seed : int
        Seeds the matching's RANSAC and the reconstruction.
    known_pairs : dict, optional
        Pairs of :func:`tie_pairs` matched elsewhere with the same ``seed``
        (:func:`.pairs.match_pair`); the rest are matched here.
    times : (N,) float ndarray, optional
        Capture times (s, NaN unknown), which let the GPS altitudes drift.
    flights : (N,) sequence of str or None, optional
        The flight each image was said to belong to (:mod:`workers.core.flights`).
    known_tiles : dict, optional
        Tiles of a large map reconstructed elsewhere, by :func:`.tiling.tile_key`
        (:mod:`workers.core.tiles`); the rest are reconstructed here.
    kept : KeptModels, optional
        COLMAP's models kept from the map's last build (:mod:`.kept`): images added since
        are registered into them; this build's are kept there in their place. The tie
        pairs are planned at the reach kept there (:func:`tie_pairs`).
    timings : dict, optional
        Receives the left-out models' seconds (:func:`.tiling.reconstruct`).

    Returns
    -------
    (MapGeometry, Structure) or None
        The geometry (its points still to add: :meth:`MapGeometry.add_points`) and the
        structure it came from.
    """
    positions = np.asarray(positions, np.float64)
    if len(positions) < 3:
        return None
    # One BLAS thread, as in the engine's workers: a map build is the same wherever it runs.
    with threadpool_limits(limits=1, user_api="blas"):
        pairs = match_pairs(keypoints, descriptors,
                            tie_pairs(positions, times, flights, kept=kept), seed=seed,
                            known=known_pairs)
        structure = reconstruct(keypoints, pairs, positions, altitudes, focal_px, seed=seed,
                                times=times, known_tiles=known_tiles, kept=kept,
                                timings=timings)
    if structure is None:
        return None
    if (structure.placed.mean() < MIN_PLACED or structure.residual_px > MAX_RESIDUAL_PX
            or structure.gps_rms_h > MAX_GPS_RMS):
        return None
    return MapGeometry.from_structure(structure), structure


def register_against(geometry: MapGeometry, kind: str, frame_px: np.ndarray,
                     matches: list[tuple[int, np.ndarray, np.ndarray]], *,
                     frame_shape: tuple[int, int], base_sigma: float | None = None,
                     rescue: bool = True) -> Registration | None:
    """A frame's pose from its matches to map images of local-feature set ``kind``.

    Parameters
    ----------
    geometry : MapGeometry
    kind : str
        Which keypoint set the map rows index (``"sift"``, ``"orb"``).
    frame_px : (K, >=2) float ndarray
        The frame's keypoints (pixels first).
    matches : list of (image, frame rows, map rows)
        Matches into each map image; map rows are global rows of the keypoint set.
    frame_shape : (height, width)
        The frame's size: its intrinsics are the map's, centred on the frame.
    base_sigma : float, optional
        The map's own accuracy (m), under the solve's; by default its self-check's.
    rescue : bool
        Three-point poses where a survey's similarity start finds no consensus
        (:func:`.register.register_frame`).
    """
    if kind not in geometry.points or not matches:
        return None
    points = geometry.points[kind]
    fp = np.concatenate([np.asarray(frame_px[q, :2], np.float64) for _, q, _ in matches])
    xyz = np.concatenate([np.asarray(points[r], np.float64) for _, _, r in matches])
    img = np.concatenate([np.full(len(q), i) for i, q, _ in matches])
    h, w = frame_shape
    k = geometry.intrinsics
    # the map's principal point is where it sits in its images; a frame of another size
    # keeps it as far from its centre
    K = Intrinsics(k.f, k.cx + (w - WORK_SIZE[0]) / 2.0, k.cy + (h - WORK_SIZE[1]) / 2.0)
    return register_frame(fp, xyz, img, K, distortion=geometry.distortion,
                          altitude_range=geometry.altitude_range(),
                          view_prior=geometry.view_prior(),
                          base_sigma=geometry.base_sigma if base_sigma is None else base_sigma,
                          rescue=rescue)


__all__ = ["Intrinsics", "KeptModels", "MapGeometry", "PairMatches", "Registration", "Structure",
           "build_geometry", "focal_from_exif", "focal_from_fov", "match_pair",
           "register_against", "tie_pairs", "tie_reach"]
