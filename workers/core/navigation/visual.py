"""Where the robot is beside the taught path, from its view of taught images.

The localiser says which taught image the frame looks like; that places the robot along
the path but not beside it, and says nothing of its heading. Li et al. close that gap with
visual servoing on the key images. Here the frame's SIFT matches with a taught image give
the essential matrix of the two views (:data:`ESSENTIAL_METHOD`): its rotation is the
robot's heading relative to the taught image, its translation the bearing at which the
taught camera sees the robot (:func:`relative_view`).

Those bearings are poor: a baseline of a metre or two against a scene 10-30 m away leaves the
direction of translation loose, and on rendered street frames it was 15-50 degrees off, so
two taught cameras' bearings do not intersect usefully. :func:`metric_view` measures the
offset itself: taught images known distances apart along the path triangulate the points
they share (:func:`triangulate_views`, fused along each keypoint's ray by :func:`fuse`), and
the frame's pose against those points (perspective-n-point) places the robot in metres beside
the path, with the solve's own uncertainty. The session weighs the bearings in its filter
where no such pose is found.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np

from ..sift import RATIO, SiftFeatures, ratio_matches

ESSENTIAL_METHOD = cv2.USAC_ACCURATE
"""The essential matrix's robust estimator: OpenCV's USAC with local optimisation and a
final fit to all inliers. Against plain RANSAC on the taught pairs of a rendered street drive
(198 pairs 1 m apart): a translation direction off by 0.9 degrees instead of 1.7 (median) and
rotation by 0.16 instead of 0.36, in 1.9 ms instead of 17 (174 pairs with about 55 matches)."""
MIN_MATCHES = 12
MIN_INLIERS = 10
MAX_REACH = 4.0
"""Metres: a pose from taught points further than this from their taught image is taken for
a wrong match."""
MAX_DEPTH = 60.0
"""Metres: triangulated points further than this (or nearer than half a metre) from the
taught camera are dropped; over a metre or two of baseline they are mostly noise."""
MAX_DEPTH_ERROR = 1.0
"""Points whose distance is more uncertain than itself (seen at a parallax under about a
third of a degree) are dropped: they say nothing about the offset beside the path."""
PIXEL_SIGMA = 1.0
"""Standard deviation of a matched keypoint (pixels at the working resolution), for the
covariance of the triangulated-point pose."""
MIN_POINT_DEPTH = 0.1
"""Metres: a pose that puts one of its points nearer the camera's plane than this (or behind
it) is not refined."""
INLIER_CHI2 = 9.21
"""99 % quantile of chi-square with 2 degrees of freedom: a matched point further than this
from a pose's reprojection, in units of its own noise, is not that pose's inlier."""
CONSENSUS_TRIES = 200
"""Most four-point poses drawn per view (fewer once the inliers found make 99.9 % sure)."""
FUSE_AGREEMENT = 3.0
"""Standard deviations: two triangulations of one taught keypoint whose depths differ by more
than this in their combined noise disagree (:func:`fuse`)."""
BASELINE_ERROR = 0.05
"""Relative error of the distance between two taught images along the relaxed path: the
scale of the triangulated points, and so of the offset measured against them."""


@dataclass(frozen=True, slots=True)
class RelativeView:
    """How a taught camera sees the robot's camera.

    ``yaw`` is the robot's heading minus the taught camera's (radians, left positive);
    ``bearing`` the direction of the robot's camera centre from the taught camera, left of
    its forward axis (radians); ``inliers`` the matches consistent with the essential matrix.
    """

    yaw: float
    bearing: float
    inliers: int


@dataclass(frozen=True, slots=True)
class MetricView:
    """The robot's camera in a taught camera's frame, in metres.

    ``forward`` and ``left`` are the robot camera's centre along and left of the taught
    camera's forward axis, ``yaw`` its heading minus the taught camera's (radians, left
    positive); ``cov`` the (3, 3) covariance of ``(forward, left, yaw)``; ``inliers`` the
    matched points the pose agrees with.
    """

    forward: float
    left: float
    yaw: float
    cov: np.ndarray
    inliers: int


class Triangulation(NamedTuple):
    """Points two taught images share, in the first one's camera frame (:func:`triangulate`).

    ``rows`` are the keypoints of that image with a point, ``points`` (n, 3) their positions
    in metres (x right, y down, z forward), ``depth_sigma`` the standard deviation of each
    point's distance along the image's ray.
    """

    rows: np.ndarray
    points: np.ndarray
    depth_sigma: np.ndarray


def camera_matrix(width: int, height: int, hfov_deg: float) -> np.ndarray:
    """(3, 3) pinhole intrinsics for a horizontal field of view, principal point central."""
    f = 0.5 * width / math.tan(math.radians(hfov_deg) / 2.0)
    return np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


def relative_view(query: SiftFeatures, ref: SiftFeatures, K: np.ndarray, *,
                  ratio: float = RATIO) -> RelativeView | None:
    """The relative pose of the robot's frame ``query`` to the taught image ``ref``.

    Camera frames are OpenCV's (x right, y down, z forward). ``recoverPose`` returns ``R, t``
    with ``x_ref = R x_query + t``: the robot's forward axis in the taught camera's frame is
    ``R @ (0, 0, 1)`` and its camera centre (``x_query = 0``) lies along ``t``. None when there
    are too few matches or inliers.
    """
    if len(query) < MIN_MATCHES or len(ref) < MIN_MATCHES:
        return None
    m = ratio_matches(np.asarray(query.descriptors, np.float32), ref.descriptors, ratio=ratio)
    if len(m) < MIN_MATCHES:
        return None
    pq = np.ascontiguousarray(query.keypoints[m[:, 0], :2], dtype=np.float64)
    pr = np.ascontiguousarray(ref.keypoints[m[:, 1], :2], dtype=np.float64)
    found = _relative_pose(pq, pr, K)
    if found is None:
        return None
    inliers, R, t, _ = found
    forward = R @ np.array([0.0, 0.0, 1.0])
    centre = t.ravel()
    # left of forward is -x in a camera frame whose x points right
    return RelativeView(yaw=math.atan2(-forward[0], forward[2]),
                        bearing=math.atan2(-centre[0], centre[2]), inliers=int(inliers))


def _relative_pose(pa: np.ndarray, pb: np.ndarray, K: np.ndarray):
    """``(inliers, R, t, mask)`` of two views from matched pixels ``pa`` and ``pb``
    (essential matrix by :data:`ESSENTIAL_METHOD`, then ``recoverPose``: ``x_b = R x_a + t``,
    ``t`` of unit length); None with fewer than :data:`MIN_INLIERS` inliers."""
    E, mask = cv2.findEssentialMat(pa, pb, K, method=ESSENTIAL_METHOD, prob=0.999,
                                   threshold=1.0)
    if E is None or E.shape != (3, 3) or mask is None or int(mask.sum()) < MIN_INLIERS:
        return None
    inliers, R, t, mask = cv2.recoverPose(E, pa, pb, K, mask=mask)
    return None if inliers < MIN_INLIERS else (int(inliers), R, t, mask)


def _match_points(a: SiftFeatures, b: SiftFeatures, ratio: float) -> tuple[np.ndarray, ...]:
    m = ratio_matches(np.asarray(a.descriptors, np.float32), b.descriptors, ratio=ratio)
    return (m, np.ascontiguousarray(a.keypoints[m[:, 0], :2], dtype=np.float64),
            np.ascontiguousarray(b.keypoints[m[:, 1], :2], dtype=np.float64))


def triangulate(ref: SiftFeatures, other: SiftFeatures, baseline: float, K: np.ndarray, *,
                ratio: float = RATIO) -> Triangulation | None:
    """3-D points of taught image ``ref`` from its matches with taught image ``other``.

    The two views' essential matrix gives their relative rotation and the direction between
    them; ``baseline`` (metres between the two along the taught path) gives the scale.

    Returns
    -------
    Triangulation or None
        None when the views share too few consistent matches. A point's depth noise is a
        keypoint's :data:`PIXEL_SIGMA` seen at the point's parallax angle: views taken along
        the path see the points ahead at almost no parallax, so it is large there.
    """
    if len(ref) < MIN_MATCHES or len(other) < MIN_MATCHES or not baseline > 0:
        return None
    m, pa, pb = _match_points(ref, other, ratio)
    if len(m) < MIN_MATCHES:
        return None
    found = _relative_pose(pa, pb, K)
    if found is None:
        return None
    _, R, t, mask = found
    keep = mask.ravel() > 0
    t = t.ravel() * baseline
    P_ref = K @ np.hstack([np.eye(3), np.zeros((3, 1))])
    P_other = K @ np.hstack([R, t[:, None]])
    X = cv2.triangulatePoints(P_ref, P_other, pa[keep].T, pb[keep].T)
    with np.errstate(divide="ignore", invalid="ignore"):
        X = (X[:3] / X[3]).T
    X_other = X @ R.T + t
    ok = ((X[:, 2] > 0.5) & (X[:, 2] < MAX_DEPTH) & (X_other[:, 2] > 0.5)
          & np.isfinite(X).all(axis=1))
    for P, px in ((P_ref, pa[keep]), (P_other, pb[keep])):
        proj = np.c_[X, np.ones(len(X))] @ P.T
        with np.errstate(divide="ignore", invalid="ignore"):
            err = np.linalg.norm(proj[:, :2] / proj[:, 2:] - px, axis=1)
        ok &= err < 2.0 * PIXEL_SIGMA
    if ok.sum() < MIN_INLIERS:
        return None
    X = X[ok]
    # depth noise along ref's ray: a keypoint's angular noise over the parallax angle
    centre_other = -R.T @ t
    to_other = X - centre_other
    cos_par = np.sum(X * to_other, axis=1) / (np.linalg.norm(X, axis=1)
                                               * np.linalg.norm(to_other, axis=1))
    sin_par = np.sqrt(np.clip(1.0 - cos_par ** 2, 1e-12, 1.0))
    depth = np.linalg.norm(X, axis=1)
    depth_sigma = depth * math.sqrt(2.0) * PIXEL_SIGMA / K[0, 0] / sin_par
    sharp = depth_sigma <= MAX_DEPTH_ERROR * depth
    if sharp.sum() < MIN_INLIERS:
        return None
    return Triangulation(m[keep, 0][ok][sharp], X[sharp], depth_sigma[sharp])


def fuse(parts: list[Triangulation | None]) -> Triangulation | None:
    """One set of points for a taught image from its triangulations with several others
    (:func:`triangulate`, each with that image first); None when there are none.

    A triangulated point reprojects onto its keypoint in the first image, so the
    triangulations of one keypoint differ in depth along its ray only. The fused point is on
    the ray of the sharpest one, at the inverse-variance mean of the depths that agree with
    it (within :data:`FUSE_AGREEMENT` of their combined noise; the others are taken for
    false matches in one of the pairs). The depths share the first image's keypoint noise,
    so the fused noise, computed as if they were independent, is somewhat optimistic; over
    pairs of different baselines it is dominated by the widest one's.
    """
    parts = [p for p in parts if p is not None and len(p.rows)]
    if not parts:
        return None
    rows = np.concatenate([p.rows for p in parts])
    points = np.concatenate([p.points for p in parts])
    sigma = np.concatenate([p.depth_sigma for p in parts])
    order = np.lexsort((sigma, rows))  # by keypoint, the sharpest first
    rows, points, sigma = rows[order], points[order], sigma[order]
    depth = np.linalg.norm(points, axis=1)
    first = np.r_[True, rows[1:] != rows[:-1]]
    group = np.cumsum(first) - 1
    lead = np.flatnonzero(first)
    agree = (np.abs(depth - depth[lead][group])
             <= FUSE_AGREEMENT * np.hypot(sigma, sigma[lead][group]))
    weight = np.where(agree, 1.0 / sigma ** 2, 0.0)
    total = np.bincount(group, weight)
    fused = np.bincount(group, weight * depth) / total
    rays = points[lead] / depth[lead][:, None]
    return Triangulation(rows[lead], rays * fused[:, None], 1.0 / np.sqrt(total))


def triangulate_views(ref: SiftFeatures, others: list[tuple[SiftFeatures, float]],
                      K: np.ndarray) -> Triangulation | None:
    """3-D points of taught image ``ref`` from its matches with each of ``others`` (their
    features and their distance from ``ref`` along the path; :func:`triangulate`), fused
    (:func:`fuse`)."""
    return fuse([triangulate(ref, other, baseline, K) for other, baseline in others])


def metric_view(query: SiftFeatures, ref: SiftFeatures, tri: Triangulation | None,
                K: np.ndarray, *, ratio: float = RATIO) -> MetricView | None:
    """The robot's pose against taught image ``ref``, from the points ``ref`` and other
    taught images triangulate (``tri``, :func:`triangulate` or :func:`triangulate_views`; it
    depends on the taught images only, so a caller keeps it from frame to frame).

    The frame's matches to those points give its pose (EPnP in RANSAC, then Gauss-Newton
    with each point weighed by its own noise, the depth noise of its triangulation
    included); the covariance is that solve's plus the scale error of the baseline
    (:data:`BASELINE_ERROR`). None when too few of the frame's matches have a point or agree
    with one pose.
    """
    if tri is None or len(query) < MIN_MATCHES:
        return None
    rows, points, depth_sigma = tri
    where = np.full(len(ref), -1)
    where[rows] = np.arange(len(rows))
    m, pq, _ = _match_points(query, ref, ratio)
    has = where[m[:, 1]] >= 0 if len(m) else np.zeros(0, bool)
    if has.sum() < MIN_INLIERS:
        return None
    obj = points[where[m[has, 1]]]
    obj_sigma = depth_sigma[where[m[has, 1]]]
    px = pq[has]
    found = _consensus_pose(obj, obj_sigma, px, K)
    if found is None:
        return None
    pose, inl = found
    refined = _weighted_pose(obj[inl], obj_sigma[inl], px[inl], K, pose)
    if refined is None:
        return None
    pose, cov_pose = refined
    state = _camera_state(pose)
    # (forward, left, yaw) as a function of the pose, differentiated numerically
    G = np.zeros((3, 6))
    for k in range(6):
        step = pose.copy()
        step[k] += 1e-7
        d = _camera_state(step) - state
        d[2] = math.remainder(d[2], 2 * math.pi)
        G[:, k] = d / 1e-7
    cov = G @ cov_pose @ G.T
    cov[:2, :2] += (BASELINE_ERROR ** 2) * np.outer(state[:2], state[:2])
    return MetricView(forward=float(state[0]), left=float(state[1]), yaw=float(state[2]),
                      cov=cov, inliers=len(inl))


def _consensus_pose(obj: np.ndarray, depth_sigma: np.ndarray, px: np.ndarray, K: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray] | None:
    """RANSAC over four-point poses (AP3P), each point judged by its own noise.

    A fixed pixel threshold is biased towards the taught camera: there, every triangulated
    point reprojects onto its keypoint whatever its depth error, while a robot a metre
    beside the path sees a point 20 m away with a depth error of a third several pixels
    from where the wrong depth puts it. Rendered street frames 1.2 m beside the path were
    placed 0.3-0.8 times as far out as they were. Here a point is an inlier when its
    reprojection error is within the 99 % ellipse of a keypoint's :data:`PIXEL_SIGMA` plus
    its depth noise seen from the pose (:func:`_mahalanobis`), the model the refinement
    weighs by. Returns the best pose ``(rvec, tvec)`` and its inliers, re-selected once
    under the refined pose; None for fewer than :data:`MIN_INLIERS`.
    """
    n = len(obj)
    if n < max(MIN_INLIERS, 4):
        return None
    rays = obj / np.linalg.norm(obj, axis=1, keepdims=True)
    rng = np.random.default_rng(n)        # the same matches give the same pose
    best, best_key, tries, needed = None, (0, 0.0), 0, CONSENSUS_TRIES
    while tries < needed:
        tries += 1
        pick = rng.choice(n, 4, replace=False)
        ok, rvec, tvec = cv2.solvePnP(obj[pick], px[pick], K, None, flags=cv2.SOLVEPNP_AP3P)
        if not ok:
            continue
        pose = np.r_[rvec.ravel(), tvec.ravel()]
        d2 = _mahalanobis(obj, rays, depth_sigma, px, K, pose)
        inl = d2 < INLIER_CHI2
        key = (int(inl.sum()), -float(np.minimum(d2, INLIER_CHI2).sum()))
        if key > best_key:
            best, best_key = (pose, inl), key
            # enough tries to draw four inliers once at 99.9 %
            w = key[0] / n
            needed = min(needed, math.ceil(math.log(1e-3) / math.log(max(1.0 - w ** 4, 1e-12))))
    if best is None or best_key[0] < MIN_INLIERS:
        return None
    pose, inl = best
    refined = _weighted_pose(obj[inl], depth_sigma[inl], px[inl], K, pose)
    if refined is None:
        return None
    pose = refined[0]
    inl = _mahalanobis(obj, rays, depth_sigma, px, K, pose) < INLIER_CHI2
    if inl.sum() < MIN_INLIERS:
        return None
    return pose, np.flatnonzero(inl)


def _mahalanobis(obj: np.ndarray, rays: np.ndarray, depth_sigma: np.ndarray, px: np.ndarray,
                 K: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Squared Mahalanobis distance of each reprojection error under the covariance
    ``PIXEL_SIGMA^2 I + depth_sigma^2 g g^T``, ``g`` the image motion of the point slid a
    metre along the taught camera's ray (Sherman-Morrison, so no 2x2 inverse per point);
    infinite behind the camera."""
    R, _ = cv2.Rodrigues(pose[:3])
    X = obj @ R.T + pose[3:]
    z = X[:, 2]
    out = np.full(len(obj), np.inf)
    front = z > 1e-6
    X, z = X[front], z[front]
    fx, fy = K[0, 0], K[1, 1]
    proj = np.c_[fx * X[:, 0] / z + K[0, 2], fy * X[:, 1] / z + K[1, 2]]
    r = proj - px[front]
    dX = rays[front] @ R.T                               # the ray, in the robot's camera
    g = np.c_[fx * (dX[:, 0] - X[:, 0] / z * dX[:, 2]) / z,
              fy * (dX[:, 1] - X[:, 1] / z * dX[:, 2]) / z]
    s2 = depth_sigma[front] ** 2
    p2 = PIXEL_SIGMA ** 2
    gr = np.sum(g * r, axis=1)
    out[front] = (np.sum(r * r, axis=1) - s2 * gr ** 2 / (p2 + s2 * np.sum(g * g, axis=1))) / p2
    return out


def _weighted_pose(obj: np.ndarray, depth_sigma: np.ndarray, px: np.ndarray, K: np.ndarray,
                   pose: np.ndarray, iterations: int = 5
                   ) -> tuple[np.ndarray, np.ndarray] | None:
    """Gauss-Newton on the reprojection errors, each whitened by its own noise: a pixel of
    :data:`PIXEL_SIGMA` plus where the point's depth noise moves its image (the point slid
    along ``ref``'s ray). Returns the pose and its covariance, scaled up where the residuals
    are larger than that noise explains; None where a point is not in front of the camera
    (a pose drawn from four points can put the others behind it, and their weights are then
    not defined)."""
    rays = obj / np.linalg.norm(obj, axis=1, keepdims=True)
    pose = pose.copy()
    for it in range(iterations + 1):
        R, _ = cv2.Rodrigues(pose[:3])
        depth = obj @ R[2] + pose[5]
        if not np.all(depth > MIN_POINT_DEPTH) or not np.all(np.isfinite(pose)):
            return None
        proj, jac = cv2.projectPoints(obj, pose[:3], pose[3:], K, None)
        r = (proj.reshape(-1, 2) - px)
        J = jac[:, :6].reshape(-1, 2, 6)
        # image motion per metre along the ray: d(projection)/d(point) = dproj/dt @ R
        g = np.einsum("nij,jk,nk->ni", jac[:, 3:6].reshape(-1, 2, 3), R, rays)
        cov = (PIXEL_SIGMA ** 2) * np.eye(2) + (depth_sigma ** 2)[:, None, None] \
            * np.einsum("ni,nj->nij", g, g)
        try:
            W = np.linalg.inv(np.linalg.cholesky(cov))  # whitening: W cov W^T = I
        except np.linalg.LinAlgError:       # weights not defined (a step gone astray)
            return None
        rw = np.einsum("nij,nj->ni", W, r).ravel()
        Jw = np.einsum("nij,njk->nik", W, J).reshape(-1, 6)
        H = Jw.T @ Jw
        if it == iterations:
            break
        try:
            step = np.linalg.solve(H, -(Jw.T @ rw))
        except np.linalg.LinAlgError:
            break
        pose += step
        if np.abs(step).max() < 1e-8:
            break
    dof = max(len(rw) - 6, 1)
    scale = max(float(rw @ rw) / dof, 1.0)
    return pose, scale * np.linalg.pinv(H)


def _camera_state(pose: np.ndarray) -> np.ndarray:
    """``(forward, left, yaw)`` of a camera with pose ``(rvec, tvec)`` (``x_cam = R x + t``)
    in the frame of the points."""
    R, _ = cv2.Rodrigues(pose[:3])
    centre = -R.T @ pose[3:]
    forward = R.T @ np.array([0.0, 0.0, 1.0])
    return np.array([centre[2], -centre[0], math.atan2(-forward[0], forward[2])])
