"""Route maps from a taught sequence (Li et al., "Partitioning for the local map" and "Loop
closure alignment").

The images of a taught route arrive in driving order with an odometry pose each. The
sequence is cut into local maps, one topological node each, whenever the current image no
longer looks like the node's first image (hue histograms, Li eq. 4), the node's features
reach a maximum, or the distance driven since the node's base (its uncertainty) reaches a
limit. A new node's base is the robot's pose at its first image; consecutive nodes are
joined by arcs holding the odometric relative pose. Loop closures, places seen again,
join a node to an earlier one that is not its neighbour; their arcs say "the same place".
Relaxation (:func:`.relaxation.relax`) then makes the node poses agree with all arcs, and
every image is placed relative to its node's relaxed base. Where absolute positions of the
images are known (GPS, or the map's own image positions), the relaxed route is moved onto
them by the rigid transform that fits best.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field

import numpy as np

from .relaxation import Arc, relative_pose, relax
from .unicycle import wrap_angle

MAX_LOOP_YAW = math.radians(25.0)
"""Largest relative yaw of a loop closure's two views."""

LOOP_VERIFIER = Callable[[int, np.ndarray], np.ndarray]
"""``verify(image, candidates) -> scores``: SIFT similarity of image ``image`` to each of
the images ``candidates`` (indices into the taught sequence), in [0, 1]."""


@dataclass(frozen=True)
class RouteParams:
    """Parameters of route building.

    Attributes
    ----------
    appearance_threshold : float
        Close the node when the Euclidean distance between the current image's hue
        histogram and the node's first image's exceeds it.
    max_features : int
        Close the node when its images' features add up to more than this.
    max_length : float
        Close the node when the robot has driven this far since its base (m).
    odometry_variance : float
        Variance an odometry arc gains per metre driven (m^2/m).
    loop_variance : float
        Variance of a loop-closure arc (m^2).
    loop_candidates : int
        Earlier images, closest in hue, that SIFT checks against each node's base image.
    loop_threshold : float
        Smallest SIFT similarity (share of matched keypoints) that closes a loop.
    loop_gate : float
        Largest odometric distance between two nodes for a loop between them, as a share of
        the distance driven between them, plus 2 m: odometry drifts, but not without bound.
    hfov_deg : float
        Horizontal field of view of the camera, for the relative yaw of a loop closure's
        two views (:func:`yaw_from_views`).
    node_variances : bool
        Relaxation weights as Li's eq. 1-3 (True) or by the arcs alone (False, the
        default: on the robot world's loop it leaves a quarter of the error eq. 1's weights
        leave; ``bench/results/nav_relaxation.md``); see :func:`.relaxation.relax`.
    """

    appearance_threshold: float = 0.5
    max_features: int = 4000
    max_length: float = 5.0
    odometry_variance: float = 0.01
    loop_variance: float = 0.05
    loop_candidates: int = 3
    loop_threshold: float = 0.2
    loop_gate: float = 0.1
    hfov_deg: float = 60.0
    node_variances: bool = False

    def __post_init__(self) -> None:
        if not isinstance(self.node_variances, bool):
            raise ValueError("node_variances must be true or false")
        for name, value in asdict(self).items():
            if name == "node_variances":
                continue
            if isinstance(value, bool) or not isinstance(value, int | float) \
                    or not math.isfinite(value) or value <= 0:
                raise ValueError(f"{name} must be a positive number, got {value!r}")
        if not isinstance(self.loop_candidates, int) or not isinstance(self.max_features, int):
            raise ValueError("loop_candidates and max_features must be integers")

    def to_params(self) -> dict:
        return asdict(self)


@dataclass
class RouteMap:
    """A built route.

    Attributes
    ----------
    node_images : (K,) int ndarray
        Index of each node's first (base) image in the taught sequence.
    node_odometry : (K, 3) float ndarray
        Each node's pose by odometry alone.
    node_poses : (K, 3) float ndarray
        Each node's pose after relaxation (and alignment, where absolute positions were
        given).
    node_variances : (K,) float ndarray
    arcs : list of Arc
        Odometry arcs between consecutive nodes, then loop closures.
    loop_arcs : int
        How many of ``arcs`` are loop closures.
    image_nodes : (N,) int ndarray
        The node each image belongs to.
    path : (N, 3) float ndarray
        Each image's pose, placed relative to its node's relaxed base: the taught path.
    sweeps : int
        Relaxation sweeps run.
    """

    node_images: np.ndarray
    node_odometry: np.ndarray
    node_poses: np.ndarray
    node_variances: np.ndarray
    arcs: list[Arc]
    loop_arcs: int
    image_nodes: np.ndarray
    path: np.ndarray
    sweeps: int
    params: dict = field(default_factory=dict)


def partition(odometry: np.ndarray, hue: np.ndarray, feature_counts: np.ndarray,
              params: RouteParams) -> np.ndarray:
    """Node of each image (Li's criteria for closing a local map).

    Parameters
    ----------
    odometry : (N, 3) float ndarray
    hue : (N, B) float ndarray
        Hue histograms.
    feature_counts : (N,) int ndarray

    Returns
    -------
    (N,) int ndarray
        Non-decreasing node numbers starting at 0.
    """
    n = len(odometry)
    nodes = np.zeros(n, np.int64)
    base, features, driven, k = 0, int(feature_counts[0]), 0.0, 0
    for i in range(1, n):
        driven += float(np.hypot(*(odometry[i, :2] - odometry[i - 1, :2])))
        different = float(np.linalg.norm(hue[i] - hue[base])) > params.appearance_threshold
        if different or features + int(feature_counts[i]) > params.max_features \
                or driven >= params.max_length:
            k += 1
            base, features, driven = i, 0, 0.0
        features += int(feature_counts[i])
        nodes[i] = k
    return nodes


def build_route(odometry: np.ndarray, hue: np.ndarray, feature_counts: np.ndarray, *,
                verify: LOOP_VERIFIER | None = None, relative_yaw=None,
                positions: np.ndarray | None = None,
                params: RouteParams | None = None) -> RouteMap:
    """Build a route map from a taught sequence.

    Parameters
    ----------
    odometry : (N, 3) float ndarray
        Odometry pose ``(x, y, theta)`` of each image, in driving order.
    hue : (N, B) float ndarray
        Hue histogram of each image (partitioning and loop candidates).
    feature_counts : (N,) int ndarray
        SIFT keypoints per image.
    verify : callable, optional
        Loop-closure check (:data:`LOOP_VERIFIER`), e.g. the hierarchical localiser's SIFT
        stage; without it no loops are closed.
    relative_yaw : callable, optional
        ``relative_yaw(image, other) -> float or None``: the heading of image ``image``
        minus that of ``other`` (radians) from their views, e.g. by the essential matrix
        (:func:`.visual.relative_view`). A loop closure then knows how the robot was turned
        when it saw the place again, instead of assuming it was turned as before.
    positions : (N, 2) float ndarray, optional
        Absolute positions of the images (GPS in the map frame; NaN where unknown); the
        relaxed route is moved onto them by the best rigid transform.
    params : RouteParams
    """
    params = params or RouteParams()
    odometry = np.asarray(odometry, np.float64)
    if odometry.ndim != 2 or odometry.shape[1] != 3 or len(odometry) < 2:
        raise ValueError("odometry must be (N, 3) with N >= 2")
    if not np.isfinite(odometry).all():
        raise ValueError("odometry holds NaN or infinite values")
    nodes = partition(odometry, hue, feature_counts, params)
    starts = np.flatnonzero(np.r_[True, np.diff(nodes) > 0])
    node_odo = odometry[starts]
    driven = np.r_[0.0, np.cumsum(np.hypot(*np.diff(odometry[:, :2], axis=0).T))]
    arcs = [Arc(k, k + 1, *relative_pose(node_odo[k], node_odo[k + 1]),
                variance=max(params.odometry_variance * (driven[starts[k + 1]] - driven[starts[k]]),
                             1e-6))
            for k in range(len(starts) - 1)]
    loops = _loop_closures(starts, nodes, odometry, driven, hue, verify, relative_yaw,
                           params) if verify else []
    result = relax(node_odo, arcs + loops, node_variances=params.node_variances)
    poses = result.poses
    image_pose = np.empty_like(odometry)
    for i in range(len(odometry)):
        k = nodes[i]
        dx, dy, dth = relative_pose(node_odo[k], odometry[i])
        c, s = math.cos(poses[k, 2]), math.sin(poses[k, 2])
        image_pose[i] = (poses[k, 0] + c * dx - s * dy, poses[k, 1] + s * dx + c * dy,
                         wrap_angle(poses[k, 2] + dth))
    if positions is not None:
        rot, shift = _rigid_fit(image_pose[:, :2], np.asarray(positions, np.float64))
        if rot is not None:
            angle = math.atan2(rot[1, 0], rot[0, 0])
            poses = _transform(poses, rot, shift, angle)
            image_pose = _transform(image_pose, rot, shift, angle)
    return RouteMap(node_images=starts, node_odometry=node_odo, node_poses=poses,
                    node_variances=result.variances, arcs=arcs + loops, loop_arcs=len(loops),
                    image_nodes=nodes, path=image_pose, sweeps=result.sweeps,
                    params=params.to_params())


def _loop_closures(starts, nodes, odometry, driven, hue, verify, relative_yaw,
                   params: RouteParams) -> list[Arc]:
    """For each node, the earlier image its base image matches best, among the hue-closest
    images of earlier, non-adjacent nodes that odometry allows. The arc joins that image's
    node to this one: this node's base sits where the matched image was taken (two images
    alike enough for SIFT were taken from about the same pose), and odometry within the
    earlier node, which has not yet drifted, places that image relative to its base."""
    loops = []
    for k in range(2, len(starts)):
        q = int(starts[k])
        earlier = np.arange(starts[k - 1])              # images of nodes before the previous
        along = driven[q] - driven[earlier]
        gap = np.hypot(*(odometry[earlier, :2] - odometry[q, :2]).T)
        earlier = earlier[(gap <= params.loop_gate * along + 2.0) & (along > 3 * params.max_length)]
        if not len(earlier):
            continue
        d = np.linalg.norm(hue[earlier] - hue[q], axis=1)
        cand = earlier[np.argsort(d, kind="stable")[: params.loop_candidates]]
        scores = np.asarray(verify(q, cand), np.float64)
        best = int(np.argmax(scores))
        if scores[best] >= params.loop_threshold:
            m = int(cand[best])
            j = int(nodes[m])
            dx, dy, dth = relative_pose(odometry[starts[j]], odometry[m])
            yaw = relative_yaw(q, m) if relative_yaw is not None else None
            if yaw is not None and abs(yaw) > MAX_LOOP_YAW:
                # a forward camera that sees a place again from so far round is more
                # likely fooled by a look-alike
                continue
            loops.append(Arc(j, k, dx, dy, dth + (yaw or 0.0), variance=params.loop_variance))
    return loops


def _rigid_fit(src: np.ndarray, dst: np.ndarray):
    """Rotation and translation taking ``src`` onto ``dst`` in least squares (Kabsch), over
    the rows where ``dst`` is finite; ``(None, None)`` with fewer than two such rows or
    when they do not span a line."""
    ok = np.isfinite(dst).all(axis=1)
    if ok.sum() < 2:
        return None, None
    a, b = src[ok], dst[ok]
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    h = (a - ca).T @ (b - cb)
    if np.linalg.norm(h) < 1e-9:
        return None, None
    u, _, vt = np.linalg.svd(h)
    rot = vt.T @ u.T
    if np.linalg.det(rot) < 0:
        vt[-1] *= -1
        rot = vt.T @ u.T
    return rot, cb - rot @ ca


def _transform(poses: np.ndarray, rot: np.ndarray, shift: np.ndarray, angle: float) -> np.ndarray:
    out = poses.copy()
    out[:, :2] = poses[:, :2] @ rot.T + shift
    out[:, 2] = wrap_angle(poses[:, 2] + angle)
    return out


def yaw_from_views(features, K: np.ndarray):
    """``relative_yaw`` for :func:`build_route` from the images' SIFT features and the
    camera matrix ``K`` (:func:`.visual.relative_view`)."""
    from .visual import relative_view

    def yaw(image: int, other: int) -> float | None:
        view = relative_view(features[image], features[other], K)
        return None if view is None else view.yaw

    return yaw


def sift_verifier(features, *, ratio: float = 0.8, verify: str = "fundamental") -> LOOP_VERIFIER:
    """The fine stage of Li et al.'s hierarchical localisation as a loop-closure check.

    Parameters
    ----------
    features : sequence of SiftFeatures
        SIFT features of every image of the taught sequence.
    ratio : float
        Lowe's ratio test.
    verify : {"none", "homography", "fundamental"}
        Geometric verification of the matches (RANSAC); a place seen again from about the
        same pose shares a fundamental matrix with it, a look-alike place does not.

    Returns
    -------
    callable
        ``verify(image, candidates)``: the share of the image's keypoints matched (and
        verified) in each candidate.
    """
    from ..localisers.scoring import verified_count
    from ..sift import ratio_matches

    def check(image: int, candidates: np.ndarray) -> np.ndarray:
        query = features[image]
        out = np.zeros(len(candidates))
        if len(query) == 0:
            return out
        q = np.asarray(query.descriptors, np.float32)
        for j, c in enumerate(candidates):
            ref = features[int(c)]
            if len(ref) == 0:
                continue
            m = ratio_matches(q, ref.descriptors, ratio=ratio)
            out[j] = verified_count(query, ref, m, verify) / len(query)
        return out

    return check
