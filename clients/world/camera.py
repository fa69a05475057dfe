"""Pinhole camera and camera poses of the synthetic worlds.

World frame: local east-north-up metres (x east, y north, z up), the tangent plane of the
world's geographic origin (:class:`workers.core.geo.GeoOrigin`). Camera frame: x right,
y down, z forward (OpenCV convention), so a world point ``P`` is seen at pixel
``K @ R @ (P - C)`` after division by its third coordinate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, slots=True)
class Camera:
    """Intrinsics of an ideal pinhole camera (no distortion).

    Attributes
    ----------
    width, height : int
        Image size in pixels.
    hfov_deg : float
        Horizontal field of view; square pixels, principal point at the image centre.
    """

    width: int = 320
    height: int = 240
    hfov_deg: float = 60.0

    @property
    def focal(self) -> float:
        """Focal length in pixels."""
        return 0.5 * self.width / math.tan(math.radians(self.hfov_deg) / 2.0)

    @property
    def matrix(self) -> np.ndarray:
        """(3, 3) float64 intrinsic matrix K; pixel centres at integer coordinates."""
        f = self.focal
        return np.array([[f, 0.0, (self.width - 1) / 2.0],
                         [0.0, f, (self.height - 1) / 2.0],
                         [0.0, 0.0, 1.0]])

    def scaled(self, factor: int) -> Camera:
        """The same field of view at ``factor`` times the resolution (supersampling)."""
        return Camera(self.width * factor, self.height * factor, self.hfov_deg)

    def frustum(self, near: float, margin: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
        """Half-spaces ``normal . X >= offset`` (camera frame) of the viewing frustum.

        Returns
        -------
        normals : (5, 3) float64 ndarray
        offsets : (5,) float64 ndarray
            Near plane first, then left, right, top, bottom, each widened by ``margin``
            pixels so that clipped polygons cover the border pixels.
        """
        k = self.matrix
        f, cx, cy = k[0, 0], k[0, 2], k[1, 2]
        x_max, y_max = self.width - 1 + margin, self.height - 1 + margin
        normals = np.array([
            [0.0, 0.0, 1.0],
            [f, 0.0, cx + margin],        # u >= -margin
            [-f, 0.0, x_max - cx],        # u <= width - 1 + margin
            [0.0, f, cy + margin],        # v >= -margin
            [0.0, -f, y_max - cy],        # v <= height - 1 + margin
        ])
        return normals, np.array([near, 0.0, 0.0, 0.0, 0.0])


@dataclass(frozen=True, slots=True)
class Pose:
    """Position and orientation of the camera.

    Attributes
    ----------
    position : (3,) float64 ndarray
        Camera centre (east, north, up) in metres.
    yaw : float
        Viewing direction in radians, counter-clockwise from east (0 = looking east,
        pi/2 = looking north).
    pitch : float
        Radians above the horizon (-pi/2 = looking straight down).
    roll : float
        Radians about the viewing direction, clockwise as seen by the camera.
    """

    position: np.ndarray
    yaw: float
    pitch: float = 0.0
    roll: float = 0.0

    @property
    def heading_deg(self) -> float:
        """Compass heading of the viewing direction: degrees clockwise from north."""
        return (90.0 - math.degrees(self.yaw)) % 360.0

    def rotation(self) -> np.ndarray:
        """(3, 3) float64 rotation R from world to camera frame (rows: right, down, forward)."""
        cy, sy = math.cos(self.yaw), math.sin(self.yaw)
        cp, sp = math.cos(self.pitch), math.sin(self.pitch)
        forward = np.array([cp * cy, cp * sy, sp])
        right = np.array([sy, -cy, 0.0])
        down = np.cross(forward, right)
        if self.roll:
            cr, sr = math.cos(self.roll), math.sin(self.roll)
            right, down = cr * right + sr * down, cr * down - sr * right
        return np.stack([right, down, forward])


def project(camera: Camera, pose: Pose, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates and depths of world points.

    Parameters
    ----------
    points : (N, 3) float ndarray
        World coordinates.

    Returns
    -------
    pixels : (N, 2) float64 ndarray
        (x, y); meaningless where ``depth <= 0``.
    depth : (N,) float64 ndarray
        Distance along the optical axis.
    """
    cam = (np.asarray(points, np.float64) - pose.position) @ pose.rotation().T
    depth = cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (cam @ camera.matrix.T)[:, :2] / depth[:, None]
    return uv, depth
