"""Relative pose of two views and the bearing triangulation, on synthetic geometry."""

import math

import numpy as np
import pytest

from vloc.workers.core.navigation.visual import (
    camera_matrix,
    intersect,
    locate,
    metric_view,
    relative_view,
    triangulate,
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


def test_intersect_by_hand():
    xy, angle = intersect((0.0, 0.0), math.radians(45), (2.0, 0.0), math.radians(135))
    assert xy == pytest.approx((1.0, 1.0))
    assert angle == pytest.approx(math.pi / 2)
    assert intersect((0.0, 0.0), 0.0, (0.0, 1.0), 0.0) is None          # parallel
    assert intersect((0.0, 0.0), math.pi, (2.0, 0.0), 0.0) is None       # behind both


def test_locate_from_two_taught_views(scene):
    pts, desc = scene
    refs = [(_view(pts, 0.0, 0.0, 0.0, desc), np.array([0.0, 0.0, 0.0])),
            (_view(pts, 1.2, 0.0, 0.0, desc), np.array([1.2, 0.0, 0.0]))]
    query = _view(pts, 1.8, -0.6, math.radians(-5.0), desc)
    xy, heading = locate(query, refs, K)
    assert xy == pytest.approx((1.8, -0.6), abs=0.1)
    assert heading == pytest.approx(math.radians(-5.0), abs=math.radians(0.5))


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
