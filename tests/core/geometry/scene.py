"""A synthetic aerial survey with exact geometry: cameras over the plane ``Z = 0``.

Ground points carry random descriptors; every camera that sees a point observes its exact
projection with the point's descriptor, so ratio-test matching between two images finds
exactly the points both see.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from vloc.workers.core.geometry.camera import Intrinsics, focal_from_fov, nadir_rotation, project
from vloc.workers.core.geometry.reconstruct import PairMatches

WIDTH, HEIGHT = 320, 240
F_TRUE = focal_from_fov(60.0, WIDTH)  # 277.13 px
K_TRUE = Intrinsics.centred(F_TRUE, WIDTH, HEIGHT)
GROUND_ALT = 212.0
"""Altitude of the ground plane in the GPS altitude frame (m)."""


def tilted_rotation(theta: float, tilt_deg: float, azimuth: float) -> np.ndarray:
    """A nadir camera with heading ``theta`` tilted by ``tilt_deg`` about a horizontal axis
    of the camera at angle ``azimuth`` from its x axis."""
    axis = np.array([np.cos(azimuth), np.sin(azimuth), 0.0])
    delta = Rotation.from_rotvec(np.radians(tilt_deg) * axis).as_matrix()
    return delta @ nadir_rotation(theta)


def tilt_deg(R: np.ndarray) -> float:
    """Angle between the viewing direction and straight down."""
    return float(np.degrees(np.arccos(np.clip(-R[2, 2], -1.0, 1.0))))


def rotation_angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """Angle of the rotation taking ``Ra`` to ``Rb``."""
    return float(np.degrees(Rotation.from_matrix(Ra @ Rb.T).magnitude()))


@dataclass
class Survey:
    rotations: np.ndarray  # (N, 3, 3)
    centres: np.ndarray  # (N, 3): east, north, height above the ground
    K: Intrinsics
    points: np.ndarray  # (P, 2) ground east/north
    descriptors: np.ndarray  # (P, 128) uint8, one per ground point
    keypoints: list[np.ndarray]  # per image (K_i, 4) float32: x, y, size, angle
    image_descriptors: list[np.ndarray]  # per image (K_i, 128) uint8
    point_ids: list[np.ndarray]  # per image (K_i,) the ground point of each keypoint

    @property
    def positions(self) -> np.ndarray:
        return self.centres[:, :2].copy()

    @property
    def altitudes(self) -> np.ndarray:
        return self.centres[:, 2] + GROUND_ALT


def survey(rng: np.random.Generator, *, rows: int = 2, cols: int = 4, spacing: float = 18.0,
           height: float = 50.0, max_tilt_deg: float = 3.0, n_points: int = 1500,
           headings: str = "lines", K: Intrinsics = K_TRUE) -> Survey:
    """A lawn-mower survey of ``rows`` x ``cols`` images, ``spacing`` metres apart.

    ``headings="lines"`` flies alternate rows in opposite directions (a few degrees of
    yaw noise), ``"random"`` gives every image any heading.
    """
    rotations, centres = [], []
    for r in range(rows):
        for c in range(cols):
            if headings == "lines":
                theta = (0.0 if r % 2 == 0 else np.pi) + np.radians(rng.normal(0.0, 3.0))
            else:
                theta = rng.uniform(-np.pi, np.pi)
            rotations.append(tilted_rotation(theta, rng.uniform(0.0, max_tilt_deg),
                                             rng.uniform(0.0, 2 * np.pi)))
            jitter = spacing / 18.0
            centres.append([c * spacing + rng.normal(0.0, jitter),
                            r * spacing + rng.normal(0.0, jitter),
                            height * (1.0 + rng.uniform(-0.06, 0.06))])
    rotations = np.stack(rotations)
    centres = np.array(centres, np.float64)
    half = height * 0.75
    lo = centres[:, :2].min(axis=0) - half
    hi = centres[:, :2].max(axis=0) + half
    points = rng.uniform(lo, hi, size=(n_points, 2))
    descriptors = rng.integers(0, 256, size=(n_points, 128), dtype=np.uint8)
    keypoints, image_desc, ids = [], [], []
    for R, C in zip(rotations, centres, strict=True):
        kp, desc, seen = observe(points, descriptors, R, C, K)
        keypoints.append(kp)
        image_desc.append(desc)
        ids.append(seen)
    return Survey(rotations, centres, K, points, descriptors, keypoints, image_desc, ids)


def observe(points: np.ndarray, descriptors: np.ndarray, R: np.ndarray, C: np.ndarray,
            K: Intrinsics = K_TRUE) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Keypoints (K, 4) float32, descriptors and ground point ids of what camera (R, C) sees."""
    px = project(R, C, K, np.column_stack([points, np.zeros(len(points))]))
    seen = np.flatnonzero(np.isfinite(px).all(axis=1) & (px[:, 0] >= 0) & (px[:, 1] >= 0)
                          & (px[:, 0] < 2 * K.cx) & (px[:, 1] < 2 * K.cy))
    kp = np.zeros((len(seen), 4), np.float32)
    kp[:, :2] = px[seen]
    kp[:, 2] = 3.0
    return kp, descriptors[seen], seen


def exact_pairs(s: Survey, rng: np.random.Generator, *, min_common: int = 10,
                max_per_pair: int = 30) -> list[PairMatches]:
    """Tie points of every pair of images that share at least ``min_common`` ground points,
    with pixels taken from the exact (float64) projections."""
    ground3 = np.column_stack([s.points, np.zeros(len(s.points))])
    out = []
    n = len(s.centres)
    for a in range(n):
        for b in range(a + 1, n):
            common = np.intersect1d(s.point_ids[a], s.point_ids[b])
            if len(common) < min_common:
                continue
            if len(common) > max_per_pair:
                common = np.sort(rng.choice(common, size=max_per_pair, replace=False))
            pa = project(s.rotations[a], s.centres[a], s.K, ground3[common])
            pb = project(s.rotations[b], s.centres[b], s.K, ground3[common])
            H, _ = cv2.findHomography(pa, pb, 0)
            out.append(PairMatches(a, b, pa, pb, H))
    return out
