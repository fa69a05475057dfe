"""Registering one frame against the reconstructed map: a metric camera pose.

A frame's keypoints are matched to those of a few map images (the best verified ones); each
matched map keypoint has a place on the ground (:func:`~.reconstruct.ground_points`), which
gives 2D-3D correspondences with ``Z = 0``. A RANSAC perspective-n-point solve on them
(OpenCV, planar points) gives the frame's camera pose: its centre is the metric position of
the device, the yaw of its image its heading. Nothing here depends on the map images' GPS
tags beyond the reconstruction's alignment, so the position is not tied to the nearest map
image.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from .camera import Intrinsics, compass_heading_deg

MIN_INLIERS: int = 12
"""Fewer PnP inliers than this and the pose is not trusted."""


@dataclass(frozen=True)
class Registration:
    """A frame's metric pose from camera geometry.

    Attributes
    ----------
    xy : (2,) float ndarray
        Camera centre, east/north (m) in the map frame.
    height : float
        Camera height above the ground plane (m).
    heading_deg : float
        Compass bearing of the image's top edge (degrees clockwise from north).
    tilt_deg : float
        Angle between the viewing direction and straight down.
    inliers : int
        PnP inliers.
    sigma : float
        Standard deviation (m, per axis) to fuse the position with.
    heading_sigma_deg : float
        Standard deviation of the heading.
    images : tuple of int
        Map images that contributed inliers.
    """

    xy: np.ndarray
    height: float
    heading_deg: float
    tilt_deg: float
    inliers: int
    sigma: float
    heading_sigma_deg: float
    images: tuple[int, ...]


def register_frame(frame_px: np.ndarray, ground_xy: np.ndarray, image_of: np.ndarray,
                   K: Intrinsics, *, height_range: tuple[float, float],
                   reproj_px: float = 4.0, max_tilt_deg: float = 35.0,
                   base_sigma: float = 2.0, iterations: int = 200,
                   rng_seed: int = 0) -> Registration | None:
    """Camera pose of a frame from its matches to map keypoints with ground positions.

    Parameters
    ----------
    frame_px : (n, 2) float ndarray
        Pixels of the frame's matched keypoints (working resolution).
    ground_xy : (n, 2) float ndarray
        Ground east/north of the map keypoints they matched.
    image_of : (n,) int ndarray
        Map image of each correspondence.
    K : Intrinsics
        The frame's camera (the map's when the device says nothing).
    height_range : (float, float)
        Plausible camera heights above ground (m); a pose outside is rejected.

    Returns
    -------
    Registration or None
        None when there are too few consistent correspondences or the pose is implausible.
    """
    ok = np.isfinite(ground_xy).all(axis=1)
    if ok.sum() < MIN_INLIERS:
        return None
    img_pts = np.ascontiguousarray(frame_px[ok], dtype=np.float64)
    obj = np.ascontiguousarray(np.column_stack([ground_xy[ok], np.zeros(ok.sum())]),
                               dtype=np.float64)
    # Centre the object points: the solvers are better conditioned near the origin.
    centre = obj.mean(axis=0)
    obj_c = obj - centre
    # The ground is a plane, so ground -> image is a homography: its RANSAC (a linear
    # four-point solve per hypothesis) finds the consistent matches several times faster
    # than a RANSAC over perspective-n-point solves, and IPPE then gives the pose from them.
    cv2.setRNGSeed(rng_seed)
    H, mask = cv2.findHomography(obj_c[:, :2], img_pts, cv2.RANSAC, reproj_px,
                                 maxIters=iterations, confidence=0.999)
    if H is None or mask is None or int(mask.sum()) < MIN_INLIERS:
        return None
    inl = np.flatnonzero(mask.ravel())
    found, rvec, tvec = cv2.solvePnP(obj_c[inl], img_pts[inl], K.matrix, None,
                                     flags=cv2.SOLVEPNP_IPPE)
    if not found:
        return None
    rvec, tvec = cv2.solvePnPRefineLM(obj_c[inl], img_pts[inl], K.matrix, None, rvec, tvec)
    # the homography's inliers are judged again under the pose (its camera is constrained)
    proj, _ = cv2.projectPoints(obj_c[inl], rvec, tvec, K.matrix, None)
    inl = inl[np.linalg.norm(proj.reshape(-1, 2) - img_pts[inl], axis=1) <= reproj_px]
    if len(inl) < MIN_INLIERS:
        return None
    R, _ = cv2.Rodrigues(rvec)
    C = -R.T @ tvec.ravel() + centre
    tilt = math.degrees(math.acos(float(np.clip(-R[2, 2], -1.0, 1.0))))
    lo, hi = height_range
    if not (lo <= C[2] <= hi) or tilt > max_tilt_deg:
        return None
    proj, _ = cv2.projectPoints(obj_c[inl], rvec, tvec, K.matrix, None)
    err = np.linalg.norm(proj.reshape(-1, 2) - img_pts[inl], axis=1)
    rms_px = float(np.sqrt(np.mean(err ** 2)))
    n = len(inl)
    # Position noise: the pixel noise seen from the camera's height, shrinking with the
    # number of inliers, on top of the map's own alignment error (base_sigma).
    metres_per_px = C[2] / K.f
    sigma = math.hypot(base_sigma, 3.0 * rms_px * metres_per_px / math.sqrt(n))
    images = tuple(sorted({int(i) for i in image_of[ok][inl]}))
    heading_sigma = math.degrees(3.0 * max(rms_px, 0.5) / K.f / math.sqrt(n)) + 0.5
    return Registration(xy=C[:2].copy(), height=float(C[2]),
                        heading_deg=compass_heading_deg(R), tilt_deg=tilt, inliers=n,
                        sigma=float(sigma), heading_sigma_deg=float(heading_sigma),
                        images=images)
