"""Where the robot is beside the taught path, from its view of two taught images.

The localiser says which taught image the frame looks like; that places the robot along
the path but not beside it, and says nothing of its heading. Li et al. close that gap with
visual servoing on the key images. Here the frame's SIFT matches with a taught image give
the essential matrix of the two views (Nister's five-point solver with RANSAC): its
rotation is the robot's heading relative to the taught image, its translation the bearing
at which the taught camera sees the robot. Two taught images a little apart along the path
see the robot at two bearings; where the two rays meet is the robot's position, beside the
path as well as along it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from ..sift import RATIO, SiftFeatures, ratio_matches

MIN_MATCHES = 12
MIN_INLIERS = 10
MIN_RAY_ANGLE = math.radians(12.0)
"""Rays meeting at a smaller angle than this place the robot too poorly along them."""
MAX_REACH = 4.0
"""Metres: a triangulated position further than this from both taught images is taken for
a wrong match."""


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
    E, mask = cv2.findEssentialMat(pq, pr, K, method=cv2.RANSAC, prob=0.999, threshold=1.0)
    if E is None or E.shape != (3, 3) or mask is None or int(mask.sum()) < MIN_INLIERS:
        return None
    inliers, R, t, _ = cv2.recoverPose(E, pq, pr, K, mask=mask)
    if inliers < MIN_INLIERS:
        return None
    forward = R @ np.array([0.0, 0.0, 1.0])
    centre = t.ravel()
    # left of forward is -x in a camera frame whose x points right
    return RelativeView(yaw=math.atan2(-forward[0], forward[2]),
                        bearing=math.atan2(-centre[0], centre[2]), inliers=int(inliers))


def intersect(p1, heading1: float, p2, heading2: float) -> tuple[np.ndarray, float] | None:
    """Where the rays from ``p1`` and ``p2`` at the given headings (radians from east) meet,
    and the angle between them; None for rays that do not meet ahead of both."""
    d1 = np.array([math.cos(heading1), math.sin(heading1)])
    d2 = np.array([math.cos(heading2), math.sin(heading2)])
    a = np.column_stack([d1, -d2])
    det = float(np.linalg.det(a))
    angle = abs(math.asin(max(-1.0, min(1.0, det))))
    if angle < 1e-6:
        return None
    lam = np.linalg.solve(a, np.asarray(p2, np.float64) - np.asarray(p1, np.float64))
    if lam[0] <= 0 or lam[1] <= 0:
        return None
    return np.asarray(p1, np.float64) + lam[0] * d1, angle


def locate(query: SiftFeatures, refs: list[tuple[SiftFeatures, np.ndarray]], K: np.ndarray
           ) -> tuple[np.ndarray, float] | None:
    """The robot's position and heading from its views of taught images.

    Parameters
    ----------
    query : SiftFeatures
    refs : list of (SiftFeatures, (3,) pose)
        Taught images near the robot along the path and their poses ``(x, y, theta)``.
    K : (3, 3) ndarray

    Returns
    -------
    xy : (2,) ndarray, heading : float
        From the pair of views whose rays meet at the widest angle (at least
        :data:`MIN_RAY_ANGLE`), within :data:`MAX_REACH` of the taught images; None when no
        pair does.
    """
    views = []
    for feats, pose in refs:
        v = relative_view(query, feats, K)
        if v is not None:
            views.append((v, np.asarray(pose, np.float64)))
    best = None
    for i in range(len(views)):
        for j in range(i + 1, len(views)):
            (vi, pi), (vj, pj) = views[i], views[j]
            hit = intersect(pi[:2], pi[2] + vi.bearing, pj[:2], pj[2] + vj.bearing)
            if hit is None or hit[1] < MIN_RAY_ANGLE:
                continue
            xy, angle = hit
            if min(np.hypot(*(xy - pi[:2])), np.hypot(*(xy - pj[:2]))) > MAX_REACH:
                continue
            if best is None or angle > best[2]:
                heading = math.atan2(math.sin(pi[2] + vi.yaw) + math.sin(pj[2] + vj.yaw),
                                     math.cos(pi[2] + vi.yaw) + math.cos(pj[2] + vj.yaw))
                best = (xy, heading, angle)
    return None if best is None else (best[0], best[1])
