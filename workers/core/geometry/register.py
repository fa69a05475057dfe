"""Registering one frame against the reconstructed map: a metric camera pose.

A frame's keypoints are matched to those of a few map images (the best verified ones); each
matched map keypoint sees a 3-D point of the map's structure (:mod:`.sfm`,
:meth:`.mapgeometry.MapGeometry.add_points`), which gives 2D-3D correspondences. A RANSAC
over minimal three-point solutions (OpenCV's AP3P) and a Levenberg-Marquardt refinement on
its consensus give the frame's camera pose: its centre is the metric position of the device,
the yaw of its image its heading. Nothing here assumes a ground plane or a camera looking
down, and nothing depends on the map images' GPS tags beyond the reconstruction's alignment,
so the position is not tied to the nearest map image.

Over flat ground seen from above, a camera's tilt and its position trade off: tilting the
camera by a few degrees and moving it by ``height * tan(tilt)`` shifts the image almost
uniformly, and where the inliers cover only part of the frame (cheap features clustered in
textured patches) the data cannot tell the two apart. At 70 m a 15 degree tilt is a 19 m
shift. Where the map's own cameras all look one way (a survey flown with a fixed gimbal:
:meth:`~.mapgeometry.MapGeometry.view_prior`), the pose is therefore refined as a maximum a
posteriori estimate, the reprojection errors together with a prior that the frame looks as
the map's cameras do, and the position's uncertainty comes from that solve's covariance:
large where the inliers leave the tilt loose, small where they pin it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from .camera import Intrinsics, compass_heading_deg

MIN_INLIERS: int = 12
"""Fewer PnP inliers than this and the pose is not trusted."""

PIXEL_SIGMA: float = 1.5
"""Standard deviation of a matched keypoint's position at the working resolution (pixels):
the weight of the reprojection errors against the tilt prior, and the floor of the noise the
pose covariance assumes."""

SAMPLE_SLACK: float = 2.0
"""The consensus of a survey camera's similarity start counts correspondences within this
many times the pose's reprojection threshold: a camera tilted by a few degrees, and relief,
bend the similarity by a few pixels at the frame's edges."""

CLEAR_CONSENSUS: float = 0.5
"""A start whose pose explains this share of the correspondences needs no other."""

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
        Camera altitude (m, in the frame of the map's GPS altitudes).
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


def register_frame(frame_px: np.ndarray, points: np.ndarray, image_of: np.ndarray,
                   K: Intrinsics, *, distortion: np.ndarray | None = None,
                   altitude_range: tuple[float, float],
                   view_prior: tuple[np.ndarray, float] | None = None,
                   reproj_px: float = 4.0, base_sigma: float = 2.0, iterations: int = 200,
                   rng_seed: int = 0, rescue: bool = True) -> Registration | None:
    """Camera pose of a frame from its matches to map keypoints with 3-D points.

    Parameters
    ----------
    frame_px : (n, 2) float ndarray
        Pixels of the frame's matched keypoints (working resolution).
    points : (n, 3) float ndarray
        East/north/altitude of the 3-D points the map keypoints they matched see; NaN
        where unknown.
    image_of : (n,) int ndarray
        Map image of each correspondence.
    K : Intrinsics
        The frame's camera (the map's when the device says nothing).
    distortion : (4,) float ndarray, optional
        OpenCV's distortion coefficients of the frame's camera.
    altitude_range : (float, float)
        Plausible camera altitudes (m); a pose outside is rejected.
    view_prior : ((3,) direction, sigma in degrees) or None
        Prior on the camera's viewing direction (east/north/up unit vector); None solves
        by the reprojection errors alone.
    base_sigma : float
        The map's own alignment error (m), under the solve's.
    rescue : bool
        With a view prior, try three-point poses also where the similarity start finds no
        consensus at all (relief can bend the similarity past its threshold); False leaves
        such a frame unregistered, for a caller with a more thorough registration to
        fall back on.

    Returns
    -------
    Registration or None
        None when there are too few consistent correspondences or the pose is implausible.
    """
    ok = np.isfinite(points).all(axis=1)
    if ok.sum() < MIN_INLIERS:
        return None
    img_pts = np.ascontiguousarray(frame_px[ok], dtype=np.float64)
    obj = np.ascontiguousarray(points[ok], dtype=np.float64)
    dist = np.zeros(4) if distortion is None else np.asarray(distortion, np.float64)
    # Centre the object points: the solvers are better conditioned near the origin.
    centre = obj.mean(axis=0)
    obj_c = obj - centre
    # A survey's frame starts from its similarity, a RANSAC of two points; three-point
    # poses are tried where it finds no clear consensus (where it finds none, only to
    # rescue), and always elsewhere.
    starts = [lambda: _p3p_start(obj_c, img_pts, K, dist, reproj_px, iterations, rng_seed)]
    if view_prior is not None:
        starts.insert(0, lambda: _similarity_start(obj_c, img_pts, K, dist, view_prior[0],
                                                   reproj_px, iterations, rng_seed))
    best = None
    for k, make in enumerate(starts):
        if best is not None and len(best[2]) >= CLEAR_CONSENSUS * len(img_pts):
            break
        if k and best is None and not rescue:
            break  # the similarity found no consensus, and no rescue is asked for
        try:
            start = make()
            if start is None:
                continue
            rvec, tvec, inl = start
            rvec, tvec = cv2.solvePnPRefineLM(obj_c[inl], img_pts[inl], K.matrix, dist,
                                              rvec, tvec)
        except cv2.error:
            # OpenCV's solvers assert on degenerate points (a consensus of the few 3-D
            # points several map keypoints share, SQPnP's "num_null_vectors"): no pose
            continue
        # every correspondence is judged again under the refined pose
        proj, _ = cv2.projectPoints(obj_c, rvec, tvec, K.matrix, dist)
        inl = np.flatnonzero(np.linalg.norm(proj.reshape(-1, 2) - img_pts, axis=1)
                             <= reproj_px)
        if best is None or len(inl) > len(best[2]):
            best = (rvec, tvec, inl)
    if best is None or len(best[2]) < MIN_INLIERS:
        return None
    rvec, tvec, inl = best
    pose = np.concatenate([rvec.ravel(), tvec.ravel()]).astype(np.float64)
    pose, cov = _map_pose(obj_c[inl], img_pts[inl], K.matrix, dist, pose, view_prior)
    R, _ = cv2.Rodrigues(pose[:3])
    C = -R.T @ pose[3:] + centre
    lo, hi = altitude_range
    if not lo <= C[2] <= hi:
        return None
    if view_prior is not None and _angle_deg(R[2], view_prior[0]) > 5.0 * view_prior[1]:
        return None
    proj, _ = cv2.projectPoints(obj_c[inl], pose[:3], pose[3:], K.matrix, dist)
    err = np.linalg.norm(proj.reshape(-1, 2) - img_pts[inl], axis=1)
    rms_px = float(np.sqrt(np.mean(err ** 2)))
    n = len(inl)
    # Position noise: the solve's covariance (pixel noise through the geometry of these
    # inliers, with the view prior), scaled up where the residuals are larger than
    # assumed, on top of the map's own alignment error (base_sigma).
    scale = max(rms_px / PIXEL_SIGMA, 1.0) ** 2
    cov_xy = scale * _centre_covariance(pose, cov)[:2, :2]
    sigma = math.sqrt(base_sigma ** 2 + float(np.linalg.eigvalsh(cov_xy)[-1]))
    images = tuple(sorted({int(i) for i in image_of[ok][inl]}))
    heading_sigma = math.degrees(3.0 * max(rms_px, 0.5) / K.f / math.sqrt(n)) + 0.5
    tilt = math.degrees(math.acos(float(np.clip(-R[2, 2], -1.0, 1.0))))
    return Registration(xy=C[:2].copy(), height=float(C[2]),
                        heading_deg=compass_heading_deg(R), tilt_deg=tilt, inliers=n,
                        sigma=float(sigma), heading_sigma_deg=float(heading_sigma),
                        images=images)


def _p3p_start(obj: np.ndarray, px: np.ndarray, K: Intrinsics, dist: np.ndarray,
               reproj_px: float, iterations: int, seed: int):
    """A RANSAC over minimal three-point poses (AP3P): ``(rvec, tvec, inliers)`` or None."""
    cv2.setRNGSeed(seed)
    found, rvec, tvec, inl = cv2.solvePnPRansac(
        obj, px, K.matrix, dist, iterationsCount=iterations, reprojectionError=reproj_px,
        confidence=0.999, flags=cv2.SOLVEPNP_AP3P)
    if not found or inl is None or len(inl) < MIN_INLIERS:
        return None
    return rvec, tvec, inl.ravel()


def _similarity_start(obj: np.ndarray, px: np.ndarray, K: Intrinsics, dist: np.ndarray,
                      direction: np.ndarray, reproj_px: float, iterations: int, seed: int):
    """A start for a camera looking along ``direction``, as a survey's cameras do.

    Seen along its viewing direction, a scene of modest relief maps to the image by nearly a
    similarity (rotation, scale, shift) of its coordinates across that direction: a
    two-point model, whose RANSAC needs about 1/w^2 samples at an inlier share w where
    three-point poses need 1/w^3, and whose consensus is not fooled by a false tilt. The
    consensus (judged at twice the pose's threshold, for the relief and tilt it leaves out)
    then gives a pose (SQPnP). Returns ``(rvec, tvec, inliers)`` or None.
    """
    d = np.asarray(direction, np.float64)
    e1 = np.cross(d, [0.0, 0.0, 1.0] if abs(d[2]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(d, e1)  # e1 x e2 = d: image x, y and the viewing direction, right-handed
    across = np.column_stack([obj @ e1, obj @ e2])
    undistorted = cv2.undistortPoints(px.reshape(-1, 1, 2), K.matrix, dist,
                                      P=K.matrix).reshape(-1, 2)
    cv2.setRNGSeed(seed)
    S, mask = cv2.estimateAffinePartial2D(across, undistorted, method=cv2.RANSAC,
                                          ransacReprojThreshold=SAMPLE_SLACK * reproj_px,
                                          maxIters=iterations, confidence=0.999,
                                          refineIters=0)
    if S is None or mask is None or int(mask.sum()) < MIN_INLIERS:
        return None
    inl = np.flatnonzero(mask.ravel())
    found, rvec, tvec = cv2.solvePnP(obj[inl], px[inl], K.matrix, dist,
                                     flags=cv2.SOLVEPNP_SQPNP)
    if not found:
        return None
    return rvec, tvec, inl


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return math.degrees(math.acos(float(np.clip(np.dot(a, b), -1.0, 1.0))))


def _viewing_direction(rvec: np.ndarray) -> np.ndarray:
    """The camera's optical axis in the world (east, north, up)."""
    R, _ = cv2.Rodrigues(rvec)
    return R[2]


def _residuals(obj: np.ndarray, px: np.ndarray, K: np.ndarray, dist: np.ndarray,
               pose: np.ndarray, view_prior: tuple[np.ndarray, float] | None,
               ) -> tuple[np.ndarray, np.ndarray]:
    """Whitened residuals of the pose and their Jacobian (6 columns: rvec, tvec).

    Reprojection errors over :data:`PIXEL_SIGMA`, then (with a prior) the difference of
    the viewing direction from the prior's over the sine of its standard deviation.
    """
    proj, jac = cv2.projectPoints(obj, pose[:3], pose[3:], K, dist)
    r = (proj.reshape(-1, 2) - px).ravel() / PIXEL_SIGMA
    J = jac[:, :6] / PIXEL_SIGMA
    if view_prior is None:
        return r, J
    direction, sigma_deg = view_prior
    s = math.sin(math.radians(sigma_deg))
    axis = _viewing_direction(pose[:3]) - direction
    J_axis = np.zeros((3, 6))
    h = 1e-7
    for k in range(3):
        step = pose[:3].copy()
        step[k] += h
        J_axis[:, k] = (_viewing_direction(step) - direction - axis) / h
    return np.concatenate([r, axis / s]), np.vstack([J, J_axis / s])


def _map_pose(obj: np.ndarray, px: np.ndarray, K: np.ndarray, dist: np.ndarray,
              pose: np.ndarray, view_prior: tuple[np.ndarray, float] | None,
              ) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Newton on :func:`_residuals` from ``pose``: the pose and its covariance (6x6)."""
    pose = pose.copy()
    for _ in range(_GN_ITERATIONS):
        r, J = _residuals(obj, px, K, dist, pose, view_prior)
        try:
            step = np.linalg.solve(J.T @ J, -(J.T @ r))
        except np.linalg.LinAlgError:  # degenerate inliers: the least-squares step
            step = np.linalg.lstsq(J, -r, rcond=None)[0]
        pose += step
        if np.abs(step).max() < _GN_TOLERANCE:
            break
    _, J = _residuals(obj, px, K, dist, pose, view_prior)
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
