"""Relative pose of two views and the bearing triangulation, on synthetic geometry."""

import math

import numpy as np
import pytest

from vloc.workers.core.navigation.visual import (
    FUSE_AGREEMENT,
    Triangulation,
    camera_matrix,
    fuse,
    metric_view,
    relative_view,
    triangulate,
    triangulate_views,
)
from vloc.workers.core.sift import SiftFeatures

K = camera_matrix(320, 240, 60.0)


def _rotation(yaw: float) -> np.ndarray:
    """World (x east, y north, z up) to camera (x right, y down, z forward) for a camera
    looking along ``yaw`` (radians from east)."""
    fwd = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    right = np.array([math.sin(yaw), -math.cos(yaw), 0.0])
    down = np.array([0.0, 0.0, -1.0])
    return np.stack([right, down, fwd])


def _view(points: np.ndarray, x: float, y: float, yaw: float, desc: np.ndarray) -> SiftFeatures:
    """Keypoints of the world points that the camera at (x, y, 1 m) sees, with their
    descriptors."""
    cam = (points - [x, y, 1.0]) @ _rotation(yaw).T
    ok = cam[:, 2] > 0.5
    uvw = cam[ok] @ K.T
    uv = uvw[:, :2] / uvw[:, 2:]
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < 320) & (uv[:, 1] >= 0) & (uv[:, 1] < 240)
    kps = np.zeros((int(inside.sum()), 4), np.float32)
    kps[:, :2] = uv[inside]
    return SiftFeatures(kps, desc[ok][inside])


@pytest.fixture(scope="module")
def scene():
    rng = np.random.default_rng(0)
    n = 400
    pts = np.c_[rng.uniform(4, 30, n), rng.uniform(-8, 8, n), rng.uniform(0, 6, n)]
    desc = rng.integers(0, 256, (n, 128)).astype(np.uint8)
    return pts, desc


def test_relative_view_recovers_yaw_and_bearing(scene):
    pts, desc = scene
    ref = _view(pts, 0.0, 0.0, 0.0, desc)
    # the robot 1.5 m ahead and 0.4 m to the left, turned 8 degrees left
    query = _view(pts, 1.5, 0.4, math.radians(8.0), desc)
    v = relative_view(query, ref, K)
    assert v is not None and v.inliers > 100
    assert v.yaw == pytest.approx(math.radians(8.0), abs=math.radians(0.5))
    assert v.bearing == pytest.approx(math.atan2(0.4, 1.5), abs=math.radians(1.0))


def test_too_few_matches_give_nothing(scene):
    pts, desc = scene
    ref = _view(pts, 0.0, 0.0, 0.0, desc)
    other = SiftFeatures(ref.keypoints[:5], ref.descriptors[:5])
    assert relative_view(other, ref, K) is None


def test_triangulate_places_the_shared_points(scene):
    pts, desc = scene
    ref = _view(pts, 0.0, 0.0, 0.0, desc)
    other = _view(pts, -1.2, 0.0, 0.0, desc)
    rows, points, depth_sigma = triangulate(ref, other, 1.2, K)
    assert len(rows) > 50
    # only points seen at enough parallax are kept, and the nearer ones are the sharper
    depth = np.linalg.norm(points, axis=1)
    assert np.all(depth_sigma <= depth)
    assert np.median(depth_sigma[depth < 10]) < np.median(depth_sigma[depth > 20])
    # back to the world: the ref camera at (0, 0, 1) looking east
    world = points @ _rotation(0.0) + [0.0, 0.0, 1.0]
    # the world point behind each of ref's keypoints, selected as _view selects them
    cam = (pts - [0.0, 0.0, 1.0]) @ _rotation(0.0).T
    front = np.flatnonzero(cam[:, 2] > 0.5)
    uvw = cam[front] @ K.T
    uv = uvw[:, :2] / uvw[:, 2:]
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < 320) & (uv[:, 1] >= 0) & (uv[:, 1] < 240)
    behind = front[inside]
    err = np.linalg.norm(world - pts[behind[rows]], axis=1)
    assert np.max(err) < 0.05


@pytest.mark.parametrize("x, y, yaw_deg", [(1.5, 0.6, 20.0), (0.5, -1.0, -20.0), (2.5, 0.0, 5.0)])
def test_metric_view_places_the_robot_beside_the_path(scene, x, y, yaw_deg):
    pts, desc = scene
    ref = _view(pts, 0.0, 0.0, 0.0, desc)
    other = _view(pts, -1.2, 0.0, 0.0, desc)
    query = _view(pts, x, y, math.radians(yaw_deg), desc)
    v = metric_view(query, ref, triangulate(ref, other, 1.2, K), K)
    assert v is not None and v.inliers > 20
    assert (v.forward, v.left) == pytest.approx((x, y), abs=0.02)
    assert v.yaw == pytest.approx(math.radians(yaw_deg), abs=math.radians(0.2))
    # the stated uncertainty: at least the baseline's scale error, and what a pixel of
    # noise in the triangulation allows; small enough to place the robot beside the path
    assert np.all(np.linalg.eigvalsh(v.cov) >= 0)
    assert 0.05 * abs(x) <= math.sqrt(v.cov[0, 0]) < 0.5
    assert math.sqrt(v.cov[1, 1]) < 0.3


def test_metric_view_scales_with_the_baseline(scene):
    pts, desc = scene
    ref = _view(pts, 0.0, 0.0, 0.0, desc)
    other = _view(pts, -1.2, 0.0, 0.0, desc)
    query = _view(pts, 1.5, 0.6, math.radians(10.0), desc)
    # a baseline said to be twice as long doubles every distance
    v = metric_view(query, ref, triangulate(ref, other, 2.4, K), K)
    assert (v.forward, v.left) == pytest.approx((3.0, 1.2), abs=0.04)


def test_metric_view_needs_shared_points(scene):
    pts, desc = scene
    ref = _view(pts, 0.0, 0.0, 0.0, desc)
    lonely = SiftFeatures(ref.keypoints[:8], ref.descriptors[:8])
    query = _view(pts, 1.0, 0.2, 0.0, desc)
    assert metric_view(query, ref, triangulate(ref, lonely, 1.2, K), K) is None
    assert triangulate(ref, lonely, 1.2, K) is None
    assert triangulate(ref, ref, 0.0, K) is None


def _tri(rows, rays, depths, sigmas) -> Triangulation:
    rays = np.asarray(rays, np.float64)
    rays = rays / np.linalg.norm(rays, axis=1, keepdims=True)
    return Triangulation(np.asarray(rows), rays * np.asarray(depths, np.float64)[:, None],
                         np.asarray(sigmas, np.float64))


def test_fuse_by_hand():
    ray = [0.0, 0.0, 1.0]
    a = _tri([3, 5], [ray, [0.1, 0.0, 1.0]], [10.0, 8.0], [1.0, 0.5])
    b = _tri([3, 7], [ray, ray], [12.0, 20.0], [2.0, 4.0])
    # keypoint 5's pair in c disagrees with a's: 8 against 14, 6 m apart, 3 sigma is 1.8
    c = _tri([5], [[0.1, 0.0, 1.0]], [14.0], [0.5])
    rows, points, sigma = fuse([a, None, b, c])
    assert rows.tolist() == [3, 5, 7]
    # keypoint 3: inverse-variance mean of 10 (sigma 1) and 12 (sigma 2)
    assert np.linalg.norm(points[0]) == pytest.approx((10 + 12 / 4) / 1.25)
    assert sigma[0] == pytest.approx(1 / math.sqrt(1.25))
    # keypoint 5: the sharpest (the first of equals) alone, on its ray
    assert np.linalg.norm(points[1]) == pytest.approx(8.0)
    assert points[1] / np.linalg.norm(points[1]) == pytest.approx(np.array([0.1, 0, 1]) / math.hypot(0.1, 1))
    assert sigma[1] == pytest.approx(0.5)
    # keypoint 7: one triangulation, as it was
    assert points[2] == pytest.approx([0.0, 0.0, 20.0]) and sigma[2] == pytest.approx(4.0)
    assert fuse([None]) is None and fuse([]) is None


def _fuse_slowly(parts):
    """Keypoint by keypoint: the sharpest triangulation, and the inverse-variance mean of the
    depths within FUSE_AGREEMENT combined sigmas of it, on its ray."""
    found = {}
    for p in parts:
        for r, x, s in zip(p.rows, p.points, p.depth_sigma, strict=True):
            found.setdefault(int(r), []).append((x, s))
    out = []
    for r in sorted(found):
        lead_x, lead_s = min(found[r], key=lambda e: e[1])
        d0 = np.linalg.norm(lead_x)
        num = den = 0.0
        for x, s in found[r]:
            if abs(np.linalg.norm(x) - d0) <= FUSE_AGREEMENT * math.hypot(s, lead_s):
                num += np.linalg.norm(x) / s ** 2
                den += 1 / s ** 2
        out.append((r, lead_x / d0 * (num / den), 1 / math.sqrt(den)))
    return out


def test_fuse_against_a_slow_reference():
    rng = np.random.default_rng(3)
    parts = []
    for _ in range(5):
        rows = np.sort(rng.choice(60, size=40, replace=False))
        rays = np.c_[rng.normal(0, 0.3, (40, 2)), np.ones(40)]
        depths = rng.uniform(3, 30, 40) * np.where(rng.random(40) < 0.2, 2.0, 1.0)
        parts.append(_tri(rows, rays, depths, rng.uniform(0.2, 3.0, 40)))
    rows, points, sigma = fuse(parts)
    slow = _fuse_slowly(parts)
    assert rows.tolist() == [r for r, _, _ in slow]
    assert points == pytest.approx(np.array([x for _, x, _ in slow]), rel=1e-12)
    assert sigma == pytest.approx(np.array([s for _, _, s in slow]), rel=1e-12)


def test_triangulate_views_fuses_the_pairs_behind_and_ahead(scene):
    pts, desc = scene
    ref = _view(pts, 0.0, 0.0, 0.0, desc)
    behind = triangulate(ref, _view(pts, -1.2, 0.0, 0.0, desc), 1.2, K)
    both = triangulate_views(ref, [(_view(pts, -1.2, 0.0, 0.0, desc), 1.2),
                                   (_view(pts, 2.4, 0.0, 0.0, desc), 2.4)], K)
    # points the camera behind does not see, and sharper depths for those both see (the
    # same where only the camera behind triangulates a point)
    assert set(behind.rows) < set(both.rows)
    fused = both.depth_sigma[np.isin(both.rows, behind.rows)]
    alone = behind.depth_sigma[np.isin(behind.rows, both.rows)]
    assert np.all(fused <= alone * (1 + 1e-12)) and np.mean(fused < 0.99 * alone) > 0.8
    world = both.points @ _rotation(0.0) + [0.0, 0.0, 1.0]
    cam = (pts - [0.0, 0.0, 1.0]) @ _rotation(0.0).T
    front = np.flatnonzero(cam[:, 2] > 0.5)
    uvw = cam[front] @ K.T
    uv = uvw[:, :2] / uvw[:, 2:]
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < 320) & (uv[:, 1] >= 0) & (uv[:, 1] < 240)
    assert np.max(np.linalg.norm(world - pts[front[inside][both.rows]], axis=1)) < 0.05
    assert triangulate_views(ref, [], K) is None


def _pose(x_right: float, yaw: float = 0.0) -> np.ndarray:
    """``(rvec, tvec)`` of a camera moved ``x_right`` metres to the right of the points'
    camera and turned ``yaw`` radians about its vertical axis (``x_cam = R x + t``)."""
    import cv2

    c, s = math.cos(yaw), math.sin(yaw)
    R = np.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]])
    rvec, _ = cv2.Rodrigues(R)
    return np.r_[rvec.ravel(), -R @ np.array([x_right, 0.0, 0.0])]


def test_mahalanobis_against_the_covariance_built_by_hand():
    """The Sherman-Morrison distance equals r^T C^-1 r with C = sigma^2 I + s^2 g g^T, g
    found by sliding the point a millimetre along the taught camera's ray and projecting."""
    import cv2

    from vloc.workers.core.navigation.visual import PIXEL_SIGMA, _mahalanobis

    rng = np.random.default_rng(3)
    obj = np.c_[rng.uniform(-8, 8, 12), rng.uniform(-2, 1, 12), rng.uniform(4, 40, 12)]
    rays = obj / np.linalg.norm(obj, axis=1, keepdims=True)
    sigma = rng.uniform(0.1, 5.0, 12)
    pose = _pose(1.1, math.radians(7.0))
    px = rng.uniform(0, 320, (12, 2))
    got = _mahalanobis(obj, rays, sigma, px, K, pose)

    def project(p):
        uv, _ = cv2.projectPoints(p[None], pose[:3], pose[3:], K, None)
        return uv.ravel()

    for i in range(12):
        g = (project(obj[i] + 1e-3 * rays[i]) - project(obj[i])) / 1e-3
        C = PIXEL_SIGMA ** 2 * np.eye(2) + sigma[i] ** 2 * np.outer(g, g)
        r = project(obj[i]) - px[i]
        assert got[i] == pytest.approx(float(r @ np.linalg.solve(C, r)), rel=1e-4)


def test_consensus_pose_with_loose_depths_and_false_matches():
    """Near points known to 5 cm, far ones off by up to their stated depth noise (half
    their distance), and one match in four false: the pose of a robot 1.2 m beside the
    taught camera and turned 8 degrees is found, with every near point an inlier and no
    false match; the same matches give the same pose."""
    import cv2

    from vloc.workers.core.navigation.visual import _consensus_pose

    rng = np.random.default_rng(7)
    near = np.c_[rng.uniform(-6, 6, 12), rng.uniform(-1.5, 1.0, 12), rng.uniform(5, 12, 12)]
    far = np.c_[rng.uniform(-25, 25, 30), rng.uniform(-6, 1.0, 30), rng.uniform(40, 120, 30)]
    truth = np.r_[near, far]
    sigma = np.r_[np.full(12, 0.05), 0.5 * far[:, 2]]
    obj = np.r_[near, far * rng.uniform(0.5, 1.5, (30, 1))]
    pose = _pose(-1.2, math.radians(8.0))
    uv, _ = cv2.projectPoints(truth, pose[:3], pose[3:], K, None)
    px = uv.reshape(-1, 2) + rng.normal(0, 0.3, (len(truth), 2))
    false = rng.choice(len(truth), 14, replace=False)
    false = false[false >= 12]          # the near points stay true, so the truth is known
    px[false] = rng.uniform([0, 0], [320, 240], (len(false), 2))

    got, inliers = _consensus_pose(obj, sigma, px, K)
    R, _ = cv2.Rodrigues(got[:3])
    assert float(-(-R.T @ got[3:])[0]) == pytest.approx(1.2, abs=0.15)
    R_true, _ = cv2.Rodrigues(pose[:3])
    assert np.degrees(np.linalg.norm(cv2.Rodrigues(R @ R_true.T)[0])) < 0.5
    assert set(range(12)) <= set(inliers.tolist())
    assert not set(false.tolist()) & set(inliers.tolist())
    again, _ = _consensus_pose(obj, sigma, px, K)
    assert np.array_equal(again, got)
    assert _consensus_pose(obj[:9], sigma[:9], px[:9], K) is None


def test_a_pose_with_a_point_behind_the_camera_is_not_refined():
    """A four-point pose can put other inliers behind the camera, where their weights are
    not defined: the refinement declines instead of failing (a service error for the
    frame)."""
    import cv2

    from vloc.workers.core.navigation.visual import _weighted_pose

    rng = np.random.default_rng(1)
    obj = np.c_[rng.uniform(-5, 5, 10), rng.uniform(-2, 1, 10), rng.uniform(6, 30, 10)]
    sigma = np.full(10, 0.5)
    truth = _pose(0.4, math.radians(3.0))
    uv, _ = cv2.projectPoints(obj, truth[:3], truth[3:], K, None)
    px = uv.reshape(-1, 2) + rng.normal(0, 0.3, (10, 2))
    refined = _weighted_pose(obj, sigma, px, K, np.zeros(6))
    assert refined is not None and np.allclose(refined[0], truth, atol=0.05)
    # a point at the camera's plane, and a pose with every point behind the camera
    near = np.r_[obj, [[0.5, 0.2, 0.05]]]
    assert _weighted_pose(near, np.r_[sigma, 0.5], np.r_[px, [[160.0, 120.0]]], K,
                          np.zeros(6)) is None
    assert _weighted_pose(obj, sigma, px, K, np.r_[0, 0, 0, 0, 0, -40.0]) is None
    # three points matched to one pixel: the steps go astray (this raised LinAlgError, a
    # server error for the frame); now no pose, or a finite one
    astray = _weighted_pose(obj[:3], sigma[:3], np.full((3, 2), 160.0), K, np.zeros(6))
    assert astray is None or np.all(np.isfinite(astray[0]))
