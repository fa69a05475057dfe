"""Registering one frame against the reconstructed map: a metric camera pose.

A frame's keypoints are matched to those of a few map images (the best verified ones); each
matched map keypoint has a place on the ground (:func:`~.reconstruct.ground_points`), which
gives 2D-3D correspondences with ``Z = 0``. A RANSAC over a ground-to-image similarity, then
a perspective-n-point solve on its consensus (OpenCV, planar points) give the frame's camera
pose: its centre is the metric position of the device, the yaw of its image its heading. Nothing here depends on the map images' GPS
tags beyond the reconstruction's alignment, so the position is not tied to the nearest map
image.

Over a plane seen from above, a camera's tilt and its position trade off: tilting the camera
by a few degrees and moving it by ``height * tan(tilt)`` shifts the image almost uniformly,
and where the inliers cover only part of the frame (cheap features clustered in textured
patches) the data cannot tell the two apart. At 70 m a 15 degree tilt is a 19 m shift. The
pose is therefore refined as a maximum a posteriori estimate, the reprojection errors
together with a prior that the camera looks roughly down (:data:`TILT_PRIOR_DEG`), and the
position's uncertainty comes from that solve's covariance: large where the inliers leave the
tilt loose, small where they pin it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from .camera import Intrinsics, compass_heading_deg

MIN_INLIERS: int = 12
"""Fewer PnP inliers than this and the pose is not trusted."""

TILT_PRIOR_DEG: float = 5.0
"""Standard deviation of the prior on the camera's tilt from straight down (degrees). UAV
mapping cameras look down within a few degrees (the seneca-uav map cameras: median 7, nine in
ten under 12); a looser prior lets clustered inliers pull a frame 15-20 m off through a false
tilt (seneca-uav, ORB registrations against the true nearest map image: mean error 5.7 m
without the prior, 4.7 m with it)."""

PIXEL_SIGMA: float = 1.5
"""Standard deviation of a matched keypoint's position at the working resolution (pixels):
the weight of the reprojection errors against the tilt prior, and the floor of the noise the
pose covariance assumes."""

SAMPLE_SLACK: float = 2.0
"""The consensus of the similarity model counts correspondences within this many times the
pose's reprojection threshold: a camera tilted by a few degrees bends the similarity by a few
pixels at the frame's edges."""

_FLIP_NORTH = np.array([1.0, -1.0])

_GN_ITERATIONS = 10
_GN_TOLERANCE = 1e-6  # radians and metres: far below the pose's own noise


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
                   tilt_prior_deg: float | None = TILT_PRIOR_DEG,
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
    tilt_prior_deg : float or None
        Standard deviation of the prior on the tilt (degrees); None solves by the
        reprojection errors alone.

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
    # Seen from roughly straight above, the ground maps to the image by a similarity
    # (rotation, scale, shift; north flipped, as image rows grow downwards): a two-point
    # model, so its RANSAC needs about 1/w^2 samples at an inlier share w where a
    # homography's four points need 1/w^4. On seneca-uav's registrations that is 0.6 ms
    # instead of 2.0 for the whole solve, with as many frames registered. The tilt the
    # similarity leaves out is covered by a threshold of twice the pose's: the pose (IPPE,
    # then Levenberg-Marquardt) then judges every correspondence at ``reproj_px``.
    cv2.setRNGSeed(rng_seed)
    S, mask = cv2.estimateAffinePartial2D(obj_c[:, :2] * _FLIP_NORTH, img_pts,
                                          method=cv2.RANSAC,
                                          ransacReprojThreshold=SAMPLE_SLACK * reproj_px,
                                          maxIters=iterations, confidence=0.999,
                                          refineIters=0)
    if S is None or mask is None or int(mask.sum()) < MIN_INLIERS:
        return None
    inl = np.flatnonzero(mask.ravel())
    found, rvec, tvec = cv2.solvePnP(obj_c[inl], img_pts[inl], K.matrix, None,
                                     flags=cv2.SOLVEPNP_IPPE)
    if not found:
        return None
    rvec, tvec = cv2.solvePnPRefineLM(obj_c[inl], img_pts[inl], K.matrix, None, rvec, tvec)
    # every correspondence is judged again under the pose (its camera is constrained)
    proj, _ = cv2.projectPoints(obj_c, rvec, tvec, K.matrix, None)
    inl = np.flatnonzero(np.linalg.norm(proj.reshape(-1, 2) - img_pts, axis=1) <= reproj_px)
    if len(inl) < MIN_INLIERS:
        return None
    pose = np.concatenate([rvec.ravel(), tvec.ravel()]).astype(np.float64)
    pose, cov = _map_pose(obj_c[inl], img_pts[inl], K.matrix, pose, tilt_prior_deg)
    R, _ = cv2.Rodrigues(pose[:3])
    C = -R.T @ pose[3:] + centre
    tilt = math.degrees(math.acos(float(np.clip(-R[2, 2], -1.0, 1.0))))
    lo, hi = height_range
    if not (lo <= C[2] <= hi) or tilt > max_tilt_deg:
        return None
    proj, _ = cv2.projectPoints(obj_c[inl], pose[:3], pose[3:], K.matrix, None)
    err = np.linalg.norm(proj.reshape(-1, 2) - img_pts[inl], axis=1)
    rms_px = float(np.sqrt(np.mean(err ** 2)))
    n = len(inl)
    # Position noise: the solve's covariance (pixel noise through the geometry of these
    # inliers, with the tilt prior), scaled up where the residuals are larger than assumed,
    # on top of the map's own alignment error (base_sigma).
    scale = max(rms_px / PIXEL_SIGMA, 1.0) ** 2
    cov_xy = scale * _centre_covariance(pose, cov)[:2, :2]
    sigma = math.sqrt(base_sigma ** 2 + float(np.linalg.eigvalsh(cov_xy)[-1]))
    images = tuple(sorted({int(i) for i in image_of[ok][inl]}))
    heading_sigma = math.degrees(3.0 * max(rms_px, 0.5) / K.f / math.sqrt(n)) + 0.5
    return Registration(xy=C[:2].copy(), height=float(C[2]),
                        heading_deg=compass_heading_deg(R), tilt_deg=tilt, inliers=n,
                        sigma=float(sigma), heading_sigma_deg=float(heading_sigma),
                        images=images)


def _optical_axis(rvec: np.ndarray) -> np.ndarray:
    """East and north components of the viewing direction: the sine of the tilt, along the
    direction the camera leans."""
    R, _ = cv2.Rodrigues(rvec)
    return R[2, :2]


def _residuals(obj: np.ndarray, px: np.ndarray, K: np.ndarray, pose: np.ndarray,
               tilt_prior_deg: float | None) -> tuple[np.ndarray, np.ndarray]:
    """Whitened residuals of the pose and their Jacobian (6 columns: rvec, tvec).

    Reprojection errors over :data:`PIXEL_SIGMA`, then (with a prior) the optical axis's
    horizontal components over the sine of the prior's standard deviation.
    """
    proj, jac = cv2.projectPoints(obj, pose[:3], pose[3:], K, None)
    r = (proj.reshape(-1, 2) - px).ravel() / PIXEL_SIGMA
    J = jac[:, :6] / PIXEL_SIGMA
    if tilt_prior_deg is None:
        return r, J
    s = math.sin(math.radians(tilt_prior_deg))
    axis = _optical_axis(pose[:3])
    J_axis = np.zeros((2, 6))
    h = 1e-7
    for k in range(3):
        step = pose[:3].copy()
        step[k] += h
        J_axis[:, k] = (_optical_axis(step) - axis) / h
    return np.concatenate([r, axis / s]), np.vstack([J, J_axis / s])


def _map_pose(obj: np.ndarray, px: np.ndarray, K: np.ndarray, pose: np.ndarray,
              tilt_prior_deg: float | None) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Newton on :func:`_residuals` from ``pose``: the pose and its covariance (6x6)."""
    pose = pose.copy()
    for _ in range(_GN_ITERATIONS):
        r, J = _residuals(obj, px, K, pose, tilt_prior_deg)
        try:
            step = np.linalg.solve(J.T @ J, -(J.T @ r))
        except np.linalg.LinAlgError:  # degenerate inliers: the least-squares step
            step = np.linalg.lstsq(J, -r, rcond=None)[0]
        pose += step
        if np.abs(step).max() < _GN_TOLERANCE:
            break
    _, J = _residuals(obj, px, K, pose, tilt_prior_deg)
    return pose, np.linalg.pinv(J.T @ J)


def _centre_covariance(pose: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Covariance (3x3) of the camera centre ``-R^T t`` from that of the pose."""
    def centre(p: np.ndarray) -> np.ndarray:
        R, _ = cv2.Rodrigues(p[:3])
        return -R.T @ p[3:]

    c0 = centre(pose)
    J = np.zeros((3, 6))
    for k in range(6):
        step = pose.copy()
        step[k] += 1e-7
        J[:, k] = (centre(step) - c0) / 1e-7
    return J @ cov @ J.T
