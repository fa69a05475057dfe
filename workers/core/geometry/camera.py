"""Pinhole cameras looking at a ground plane.

The map frame is east-north-up (metres, :mod:`workers.core.geo`); the ground is the plane
``Z = 0`` of that frame. A camera has a rotation ``R`` (world -> camera, rows are the camera's
axes in world coordinates), a centre ``C`` and one focal length ``f`` in pixels with the
principal point at the image centre. Camera axes follow OpenCV: x right in the image, y down,
z along the viewing direction, so a pixel is ``u = f x / z + cx``, ``v = f y / z + cy``.

A camera looking straight down with heading ``theta`` (the image's right edge pointing
``theta`` anticlockwise from east) has the rows ``(cos t, sin t, 0)``, ``(sin t, -cos t, 0)``,
``(0, 0, -1)`` (:func:`nadir_rotation`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Intrinsics:
    """Focal length and principal point in pixels at the working resolution."""

    f: float
    cx: float
    cy: float

    @property
    def matrix(self) -> np.ndarray:
        return np.array([[self.f, 0.0, self.cx], [0.0, self.f, self.cy], [0.0, 0.0, 1.0]])

    @classmethod
    def centred(cls, f: float, width: int, height: int) -> Intrinsics:
        return cls(float(f), width / 2.0, height / 2.0)


DEFAULT_HFOV_DEG: float = 65.0
"""Horizontal field of view assumed when a camera says nothing of its lens (a typical
compact or phone camera; the map reconstruction refines it)."""


def focal_from_exif(focal_mm: float | None, plane_res_px_per_mm: float | None,
                    exif_width: int | None, width: int) -> float | None:
    """Focal length in pixels at ``width`` from EXIF's focal length and focal-plane resolution.

    ``f_px = focal_mm * plane_res * width / exif_width``: the focal-plane resolution is in
    pixels per millimetre of the sensor at the EXIF image width. None when anything is missing
    or implausible.
    """
    values = (focal_mm, plane_res_px_per_mm, exif_width)
    if any(v is None or not math.isfinite(float(v)) or float(v) <= 0 for v in values):
        return None
    f = float(focal_mm) * float(plane_res_px_per_mm) * width / float(exif_width)
    # Between a fisheye-ish 150 degrees and a 5 degree telephoto.
    if not 0.13 * width <= f <= 11.5 * width:
        return None
    return f


def focal_from_fov(hfov_deg: float, width: int) -> float:
    """Focal length in pixels of a horizontal field of view over ``width`` pixels."""
    return width / 2.0 / math.tan(math.radians(hfov_deg) / 2.0)


def nadir_rotation(theta: float) -> np.ndarray:
    """World -> camera rotation of a camera looking straight down with heading ``theta``."""
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, s, 0.0], [s, -c, 0.0], [0.0, 0.0, -1.0]])


def image_heading(R: np.ndarray) -> float:
    """Heading (radians, anticlockwise from east) of the image's right edge on the ground."""
    return math.atan2(R[0, 1], R[0, 0])


def compass_heading_deg(R: np.ndarray) -> float:
    """The camera's heading as a compass bearing (degrees from north, clockwise): where the
    top of the image points, for a camera looking more down than ahead (a survey's); where
    it looks, for one looking more ahead than down (a phone's, a robot's)."""
    if -R[2, 2] < math.cos(math.radians(45.0)):
        # looking ahead: the viewing direction (+z of the camera) on the ground
        east, north = R[2, 0], R[2, 1]
    else:
        # looking down: the image's up direction (-y of the camera) on the ground
        east, north = -R[1, 0], -R[1, 1]
    return math.degrees(math.atan2(east, north)) % 360.0


def project(R: np.ndarray, C: np.ndarray, K: Intrinsics, X: np.ndarray) -> np.ndarray:
    """World points (n, 3) -> pixels (n, 2). Points behind the camera give NaN."""
    pc = (np.asarray(X, np.float64) - C) @ R.T
    z = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K.f * pc[:, 0] / z + K.cx
        v = K.f * pc[:, 1] / z + K.cy
    bad = z <= 1e-9
    u[bad] = np.nan
    v[bad] = np.nan
    return np.stack([u, v], axis=1)


def backproject_to_ground(R: np.ndarray, C: np.ndarray, K: Intrinsics,
                          pixels: np.ndarray) -> np.ndarray:
    """Pixels (n, 2) -> ground points (n, 2) where their rays meet ``Z = 0``.

    Rays that do not descend towards the ground give NaN.
    """
    px = np.asarray(pixels, np.float64)
    rays_c = np.stack([(px[:, 0] - K.cx) / K.f, (px[:, 1] - K.cy) / K.f,
                       np.ones(len(px))], axis=1)
    rays = rays_c @ R  # camera -> world: R.T @ ray, for each row
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -C[2] / rays[:, 2]
    t[~(t > 0)] = np.nan
    return C[:2] + t[:, None] * rays[:, :2]
