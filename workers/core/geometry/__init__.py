"""Camera geometry: metric positions beyond the nearest map image.

At map build, :func:`build_geometry` reconstructs the map cameras over the ground plane
(:mod:`.reconstruct`) and places every stored keypoint on the ground (:mod:`.mapgeometry`).
Per frame, :func:`register_against` matches the frame's keypoints to a few map images and
solves its camera pose (:mod:`.register`). Maps whose images do not look at one plane
(street-level robots and phones) fail the reconstruction's checks and get no geometry; the
localisers then fall back to a match-weighted position between the best verified map images.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy.spatial import cKDTree
from threadpoolctl import threadpool_limits

from .camera import Intrinsics, focal_from_exif, focal_from_fov
from .mapgeometry import MapGeometry
from .pairs import PairMatches, candidate_pairs, match_pair, match_pairs
from .reconstruct import BlockResult, PlaneReconstruction, reconstruct_in_blocks
from .register import Registration, register_frame

MAX_RESIDUAL_PX: float = 4.0
"""A reconstruction whose median tie-point error exceeds this is not a plane seen from above."""

MAX_GPS_RMS: float = 15.0
"""... nor one whose cameras sit further than this (m RMS) from their GPS tags."""

MIN_HEIGHT: float = 5.0
"""... nor one whose cameras are lower than this above the ground (m)."""

MIN_RECONSTRUCTED: float = 0.3
"""... nor one that places fewer than this share of the map images."""

MAX_HEIGHT_DISAGREEMENT: float = 0.2
"""... nor one whose camera heights disagree with the images' GPS altitudes: the standard
deviation of (height - altitude above the fitted ground) over the median height. A
street-level map (a robot's, a phone's) can pass the other checks by explaining its forward
views as a low survey looking down, with heights that its altitudes do not follow: 0.29 on
the synthetic robot world, where the survey worlds give 0.10 (UAV, 20 m up) and seneca-uav
0.035. Maps without altitudes are not judged by it."""


def tie_reach(positions: np.ndarray) -> float:
    """How far apart (m) two map images may be for their tie points to be matched: footprints
    overlap over a few spacings, so three median spacings to the nearest image."""
    # A KD-tree, not a distance matrix: the matrix of a 50,000-image map is 20 GB.
    nearest, _ = cKDTree(positions).query(positions, k=2)
    return max(3.0 * float(np.median(nearest[:, 1])), 1.0)


def tie_pairs(positions: np.ndarray) -> list[tuple[int, int]]:
    """The pairs of map images whose tie points :func:`build_geometry` matches."""
    positions = np.asarray(positions, np.float64)
    if len(positions) < 3:
        return []
    return candidate_pairs(positions, max_distance=tie_reach(positions))


def build_geometry(keypoints: Sequence[np.ndarray], descriptors: Sequence[np.ndarray],
                   positions: np.ndarray, altitudes: np.ndarray, K0: Intrinsics, *,
                   seed: int = 0,
                   known_pairs: dict[tuple[int, int], PairMatches | None] | None = None,
                   known_blocks: dict[str, BlockResult | None] | None = None,
                   ) -> MapGeometry | None:
    """Reconstruct the map cameras, or None when the map is not a plane seen from above.

    Parameters
    ----------
    keypoints, descriptors : sequences, one entry per map image
        Local features (pixels in the first two keypoint columns; SIFT descriptors), read
        by index as the pairs not in ``known_pairs`` are matched.
    positions : (N, 2) float ndarray
        East/north of the map images (GPS).
    altitudes : (N,) float ndarray
        GPS altitudes, NaN where unknown.
    K0 : Intrinsics
        Initial camera intrinsics (EXIF or an assumed field of view).
    seed : int
        Seeds the matching's RANSAC and tie-point draws, pair by pair.
    known_pairs : dict, optional
        Pairs of :func:`tie_pairs` matched elsewhere with the same ``seed``
        (:func:`.pairs.match_pair`); the rest are matched here.
    known_blocks : dict, optional
        Blocks of a large map adjusted elsewhere, by their
        :func:`.reconstruct.block_key`; the rest are adjusted here.
    """
    positions = np.asarray(positions, np.float64)
    if len(positions) < 3:
        return None
    # The incremental reconstruction amplifies rounding: the same tie points solved with
    # OpenBLAS on one thread and on two give focal lengths 0.4 px and camera centres up to
    # 0.4 m apart. One BLAS thread, as in the engine's workers, makes a map build the same
    # wherever it runs.
    with threadpool_limits(limits=1, user_api="blas"):
        pairs = match_pairs(keypoints, descriptors, positions,
                            max_distance=tie_reach(positions), seed=seed, known=known_pairs)
        rec = reconstruct_in_blocks(pairs, positions, np.asarray(altitudes, np.float64), K0,
                                    known=known_blocks)
    done = rec.reconstructed
    if done.mean() < MIN_RECONSTRUCTED or not math.isfinite(rec.residual_px):
        return None
    heights = rec.centres[done, 2]
    if (rec.residual_px > MAX_RESIDUAL_PX or rec.gps_rms > MAX_GPS_RMS
            or np.median(heights) < MIN_HEIGHT
            or height_disagreement(rec, altitudes) > MAX_HEIGHT_DISAGREEMENT):
        return None
    return MapGeometry.from_reconstruction(rec)


def height_disagreement(rec: PlaneReconstruction, altitudes: np.ndarray) -> float:
    """Spread of the reconstructed heights about the GPS altitudes above the ground each
    camera was adjusted over (its block's), over the median height: 0 where fewer than three
    reconstructed images have an altitude."""
    offsets = rec.height_offsets(altitudes)
    known = np.isfinite(offsets)
    if known.sum() < 3:
        return 0.0
    return float(np.std(offsets[known]) / np.median(rec.centres[rec.reconstructed, 2]))


def register_against(geometry: MapGeometry, kind: str, frame_px: np.ndarray,
                     matches: list[tuple[int, np.ndarray, np.ndarray]], *,
                     frame_shape: tuple[int, int]) -> Registration | None:
    """A frame's pose from its matches to map images of local-feature set ``kind``.

    Parameters
    ----------
    geometry : MapGeometry
    kind : str
        Which keypoint set the map rows index (``"sift"``).
    frame_px : (K, >=2) float ndarray
        The frame's keypoints (pixels first).
    matches : list of (image, frame rows, map rows)
        Matches into each map image; map rows are global rows of the keypoint set.
    frame_shape : (height, width)
        The frame's size: its intrinsics are the map's, centred on the frame.
    """
    if kind not in geometry.ground or not matches:
        return None
    ground = geometry.ground[kind]
    fp = np.concatenate([np.asarray(frame_px[q, :2], np.float64) for _, q, _ in matches])
    gx = np.concatenate([np.asarray(ground[r], np.float64) for _, _, r in matches])
    img = np.concatenate([np.full(len(q), i) for i, q, _ in matches])
    h, w = frame_shape
    K = Intrinsics(geometry.intrinsics.f, w / 2.0, h / 2.0)
    return register_frame(fp, gx, img, K, height_range=geometry.height_range())


__all__ = ["BlockResult", "Intrinsics", "MapGeometry", "PairMatches", "Registration", "build_geometry",
           "focal_from_exif", "focal_from_fov", "height_disagreement", "match_pair",
           "register_against", "tie_pairs", "tie_reach"]
