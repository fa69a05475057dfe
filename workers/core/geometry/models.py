"""COLMAP's models on the map's GPS, and the map's cameras joined from them.

A run of COLMAP's mapper (:mod:`.sfm`) gives one or several models, each in a frame and at a
scale of its own. Each is brought onto its images' GPS tags (:func:`tags`) by a robust
similarity weighted per axis (:func:`.align.align_to_gps`: altitudes looser than positions,
:data:`GPS_SIGMA_H` and :data:`GPS_SIGMA_V`), its cameras far from their GPS dropped
(:func:`align_models`): a :class:`TileModel`. The models of a map, from one run or from its
tiles' (:mod:`.tiling`), are then joined into its cameras (:func:`structure_of`): a
:class:`Structure` in the map's local east-north-up frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .align import align_to_gps
from .camera import Intrinsics

COLMAP_SCALE: float = 2.0
"""COLMAP's pixels per working-resolution pixel: tie points are extracted at twice the
working resolution."""

GPS_SIGMA_H: float = 5.0
"""Horizontal standard deviation of a map image's GPS position (m)."""

GPS_SIGMA_V: float = 15.0
"""Vertical standard deviation of its GPS altitude (m): consumer GPS altitudes are several
times worse than positions, and drift."""


@dataclass(frozen=True)
class Structure:
    """The map's reconstruction in its local east-north-up frame.

    Attributes
    ----------
    rotations : (N, 3, 3) float64
        World -> camera rotation of each map image; NaN where not placed.
    centres : (N, 3) float64
        Camera centre (east, north, altitude in the GPS altitudes' frame); NaN where not
        placed.
    intrinsics : Intrinsics
        Focal length and principal point at the working resolution (OpenCV's pixels).
    k1 : float
        Radial distortion (OpenCV's first coefficient, on normalised coordinates).
    observations : list of (K_i,) int64 ndarray
        Per image, the tie points (indices) that see a 3-D point.
    points : list of (K_i, 3) float64 ndarray
        Their 3-D points.
    residual_px : float
        Mean reprojection error of the 3-D points (working-resolution pixels).
    gps_rms_h, gps_rms_v : float
        RMS distance of the placed cameras from their GPS tags, horizontally and vertically.
    models : int
        How many of COLMAP's models the map's cameras come from.
    """

    rotations: np.ndarray
    centres: np.ndarray
    intrinsics: Intrinsics
    k1: float
    observations: list[np.ndarray]
    points: list[np.ndarray]
    residual_px: float
    gps_rms_h: float
    gps_rms_v: float
    models: int

    @property
    def placed(self) -> np.ndarray:
        """(N,) bool: which map images have a camera."""
        return np.isfinite(self.centres[:, 0])


def tags(positions: np.ndarray, altitudes: np.ndarray,
         times: np.ndarray | None = None) -> np.ndarray:
    """(N, 4) east, north, altitude and capture time (NaN unknown) of the map images: what
    the alignment reads of each."""
    n = len(positions)
    t = np.full(n, np.nan) if times is None else np.asarray(times, np.float64)
    return np.column_stack([np.asarray(positions, np.float64),
                            np.asarray(altitudes, np.float64), t])


@dataclass
class TileModel:
    """One of COLMAP's models, aligned to GPS: per placed image (map index) its pose,
    observed tie points and their 3-D points, with the model's camera (COLMAP's f, cx, cy,
    k at :data:`COLMAP_SCALE`) and mean reprojection error."""

    images: np.ndarray
    rotations: np.ndarray
    centres: np.ndarray
    observations: list[np.ndarray]
    points: list[np.ndarray]
    camera: np.ndarray  # COLMAP's f, cx, cy, k
    residual_px: float


def align_models(recs: list, gps: np.ndarray, seed: int) -> list[TileModel] | None:
    """COLMAP's models, in order, each aligned to ``gps``; those the alignment refuses
    left out."""
    rng = np.random.default_rng(seed)
    aligned = [m for m in (_aligned(rec, gps, rng) for rec in recs) if m is not None]
    return aligned or None


def _aligned(rec, gps: np.ndarray, rng: np.random.Generator) -> TileModel | None:
    """A COLMAP model on the map's GPS, without the cameras the alignment refuses."""
    images, rotations, centres, observations, points = [], [], [], [], []
    for image in rec.images.values():
        if not image.has_pose:
            continue
        pose = image.cam_from_world()
        R = np.asarray(pose.rotation.matrix(), np.float64)
        t = np.asarray(pose.translation, np.float64)
        idx, xyz = [], []
        for k, p2 in enumerate(image.points2D):
            if p2.has_point3D():
                idx.append(k)
                xyz.append(rec.points3D[p2.point3D_id].xyz)
        images.append(int(image.name))
        rotations.append(R)
        centres.append(-R.T @ t)
        observations.append(np.asarray(idx, np.int64))
        points.append(np.asarray(xyz, np.float64).reshape(-1, 3))
    if len(images) < 3:
        return None
    images_a = np.asarray(images, np.int64)
    rotations_a, centres_a = np.asarray(rotations), np.asarray(centres)
    found = align_to_gps(centres_a, rotations_a[:, 0, :], gps[images_a, :3],
                         axes=rotations_a, times=gps[images_a, 3],
                         sigma_h=GPS_SIGMA_H, sigma_v=GPS_SIGMA_V, rng=rng)
    if found is None:
        return None
    sim, inliers = found
    if inliers.sum() < 3:
        return None
    keep = np.flatnonzero(inliers)
    camera = np.asarray(next(iter(rec.cameras.values())).params, np.float64)
    return TileModel(images_a[keep], sim.apply_to_rotations(rotations_a[keep]),
                  sim.apply(centres_a[keep]),
                  [observations[k] for k in keep],
                  [sim.apply(points[k]) if len(points[k]) else points[k] for k in keep],
                  camera, float(rec.compute_mean_reprojection_error()) / COLMAP_SCALE)


def placed_images(models: list[TileModel] | None) -> np.ndarray:
    """The distinct images the models place, ascending."""
    if not models:
        return np.zeros(0, np.int64)
    return np.unique(np.concatenate([m.images for m in models]))


def structure_of(models: list[TileModel], n: int, gps: np.ndarray) -> Structure | None:
    """One set of cameras from the aligned models: an image placed by several models takes
    the largest's pose; the intrinsics are the largest model's."""
    models = sorted(models, key=lambda m: -len(m.images))
    rotations = np.full((n, 3, 3), np.nan)
    centres = np.full((n, 3), np.nan)
    observations = [np.zeros(0, np.int64) for _ in range(n)]
    points = [np.zeros((0, 3)) for _ in range(n)]
    used = 0
    for m in models:
        took = False
        for k, i in enumerate(m.images.tolist()):
            if np.isfinite(centres[i, 0]):
                continue
            rotations[i], centres[i] = m.rotations[k], m.centres[k]
            observations[i], points[i] = m.observations[k], m.points[k]
            took = True
        used += took
    placed = np.isfinite(centres[:, 0])
    if placed.sum() < 3:
        return None
    f, cx, cy, k = models[0].camera
    d = centres[placed] - gps[placed, :3]
    has_alt = np.isfinite(d[:, 2])
    return Structure(
        rotations, centres,
        Intrinsics(f / COLMAP_SCALE, cx / COLMAP_SCALE - 0.5, cy / COLMAP_SCALE - 0.5),
        float(k), observations, points,
        residual_px=float(np.average([m.residual_px for m in models],
                                     weights=[len(m.images) for m in models])),
        gps_rms_h=float(np.sqrt(np.mean(np.sum(d[:, :2] ** 2, axis=1)))),
        gps_rms_v=float(np.sqrt(np.mean(d[has_alt, 2] ** 2))) if has_alt.any() else math.nan,
        models=used)
