"""Pinhole cameras over the ground plane: known answers, round trips, EXIF focal lengths."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.core.geometry.scene import tilted_rotation
from vloc.workers.core.geometry.camera import (
    Intrinsics,
    backproject_to_ground,
    compass_heading_deg,
    focal_from_exif,
    focal_from_fov,
    image_heading,
    nadir_rotation,
    project,
)

K = Intrinsics(100.0, 160.0, 120.0)


def _random_pose(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    R = tilted_rotation(rng.uniform(-np.pi, np.pi), rng.uniform(0.0, 30.0),
                        rng.uniform(0.0, 2 * np.pi))
    C = np.array([rng.uniform(-500, 500), rng.uniform(-500, 500), rng.uniform(5.0, 150.0)])
    return R, C


def test_intrinsics_matrix_and_centred():
    k = Intrinsics.centred(250.0, 320, 240)
    assert (k.cx, k.cy) == (160.0, 120.0)
    np.testing.assert_array_equal(k.matrix, [[250, 0, 160], [0, 250, 120], [0, 0, 1]])


def test_nadir_camera_known_pixels():
    # Heading 0: the image's right edge points east, its top north.
    R, C = nadir_rotation(0.0), np.array([10.0, 20.0, 50.0])
    # One focal length right of centre is 45 degrees east of straight down: 50 m east.
    px = np.array([[160.0, 120.0], [260.0, 120.0], [160.0, 220.0], [110.0, 70.0]])
    expected = np.array([[10.0, 20.0], [60.0, 20.0], [10.0, -30.0], [-15.0, 45.0]])
    np.testing.assert_allclose(backproject_to_ground(R, C, K, px), expected, atol=1e-9)
    ground = np.column_stack([expected, np.zeros(4)])
    np.testing.assert_allclose(project(R, C, K, ground), px, atol=1e-9)


@pytest.mark.parametrize("seed", range(5))
def test_project_backproject_round_trip(seed):
    rng = np.random.default_rng(seed)
    for _ in range(20):
        R, C = _random_pose(rng)
        px = rng.uniform([0, 0], [320, 240], size=(50, 2))
        ground = backproject_to_ground(R, C, K, px)
        assert np.isfinite(ground).all()
        back = project(R, C, K, np.column_stack([ground, np.zeros(len(ground))]))
        np.testing.assert_allclose(back, px, atol=1e-7)
        # ... and from the ground: points under the camera project and come back.
        pts = C[:2] + rng.uniform(-0.3, 0.3, size=(50, 2)) * C[2]
        px2 = project(R, C, K, np.column_stack([pts, np.zeros(len(pts))]))
        np.testing.assert_allclose(backproject_to_ground(R, C, K, px2), pts, atol=1e-7)


def test_project_behind_camera_is_nan():
    R, C = nadir_rotation(0.3), np.array([0.0, 0.0, 40.0])
    out = project(R, C, K, np.array([[1.0, 2.0, 0.0], [1.0, 2.0, 60.0], [0.0, 0.0, 40.0]]))
    assert np.isfinite(out[0]).all()
    assert np.isnan(out[1:]).all()


def test_rays_above_the_horizon_miss_the_ground():
    # Pitched up 80 degrees from straight down: the top of the image sees the sky.
    R = tilted_rotation(0.0, 80.0, 0.0)
    C = np.array([0.0, 0.0, 30.0])
    out = backproject_to_ground(R, C, K, np.array([[160.0, 0.0], [160.0, 239.0]]))
    assert np.isnan(out).sum() == 2
    assert np.isfinite(out).any()


@pytest.mark.parametrize("theta", np.linspace(-np.pi, np.pi, 13))
def test_nadir_rotation_is_proper(theta):
    R = nadir_rotation(theta)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R[2], [0.0, 0.0, -1.0])  # looks straight down
    assert image_heading(R) == pytest.approx(math.atan2(math.sin(theta), math.cos(theta)))


@pytest.mark.parametrize(("theta_deg", "bearing"), [
    (0.0, 0.0), (90.0, 270.0), (-90.0, 90.0), (180.0, 180.0), (30.0, 330.0), (-45.0, 45.0),
])
def test_compass_heading_of_nadir_camera(theta_deg, bearing):
    R = nadir_rotation(math.radians(theta_deg))
    assert compass_heading_deg(R) % 360.0 == pytest.approx(bearing % 360.0, abs=1e-9)
    # The bearing is where the top of the image points: a ground point 10 m along it
    # appears straight above the image centre.
    b = math.radians(bearing)
    C = np.array([5.0, -3.0, 40.0])
    target = np.array([[C[0] + 10 * math.sin(b), C[1] + 10 * math.cos(b), 0.0]])
    u, v = project(R, C, K, target)[0]
    assert u == pytest.approx(K.cx, abs=1e-9)
    assert v < K.cy


def test_compass_heading_ignores_small_tilt():
    R = tilted_rotation(math.radians(-60.0), 5.0, 1.0)
    assert compass_heading_deg(R) == pytest.approx(60.0, abs=0.5)


@pytest.mark.parametrize(("hfov", "width", "expected"), [
    (90.0, 320, 160.0),
    (60.0, 320, 160.0 / math.tan(math.radians(30.0))),  # 277.128
    (65.0, 320, 251.16),
    (53.13010235, 640, 640.0),  # tan(26.565 deg) = 1/2
])
def test_focal_from_fov(hfov, width, expected):
    assert focal_from_fov(hfov, width) == pytest.approx(expected, rel=1e-4)


def test_focal_from_exif_canon_elph_300_hs():
    # 4.3 mm lens; FocalPlaneXResolution 16393.44 px/inch = 645.41 px/mm at 4000 px across.
    # 4.3 * 645.41 = 2775.3 px at 4000 px, so 222.0 px at 320.
    f = focal_from_exif(4.3, 16393.44 / 25.4, 4000, 320)
    assert f == pytest.approx(4.3 * 645.41 * 320 / 4000, rel=1e-5)
    assert f == pytest.approx(222.0, abs=0.05)


def test_focal_from_exif_35mm_equivalent():
    # A 36 mm wide frame: 1 px per mm at 36 px across; 24 mm equivalent at 320 px.
    assert focal_from_exif(24.0, 1.0, 36.0, 320) == pytest.approx(24.0 * 320 / 36.0)


@pytest.mark.parametrize(("focal_mm", "res", "exif_width"), [
    (None, 645.41, 4000), (4.3, None, 4000), (4.3, 645.41, None),
    (0.0, 645.41, 4000), (-4.3, 645.41, 4000), (4.3, 0.0, 4000), (4.3, 645.41, 0),
    (float("nan"), 645.41, 4000), (4.3, float("inf"), 4000),
    (1000.0, 645.41, 4000),  # 2.6 degrees across: beyond any telephoto
    (0.1, 645.41, 4000),  # 5 px at 320 across: wider than a fisheye
])
def test_focal_from_exif_implausible_is_none(focal_mm, res, exif_width):
    assert focal_from_exif(focal_mm, res, exif_width, 320) is None


def test_focal_from_exif_plausible_bounds():
    # 0.13 and 11.5 widths are the limits, inclusive.
    assert focal_from_exif(0.13 * 320, 1.0, 320, 320) == pytest.approx(0.13 * 320)
    assert focal_from_exif(11.5 * 320, 1.0, 320, 320) == pytest.approx(11.5 * 320)
    assert focal_from_exif(0.129 * 320, 1.0, 320, 320) is None
    assert focal_from_exif(11.6 * 320, 1.0, 320, 320) is None


def test_random_rotation_backprojection_matches_ray_plane_reference():
    """backproject_to_ground against a ray-plane intersection written out point by point."""
    rng = np.random.default_rng(7)
    for _ in range(10):
        R, C = _random_pose(rng)
        px = rng.uniform([0, 0], [320, 240], size=(5, 2))
        got = backproject_to_ground(R, C, K, px)
        for (u, v), g in zip(px, got, strict=True):
            d_cam = [(u - K.cx) / K.f, (v - K.cy) / K.f, 1.0]
            d = [sum(R[r][i] * d_cam[r] for r in range(3)) for i in range(3)]
            t = -C[2] / d[2]
            assert g == pytest.approx([C[0] + t * d[0], C[1] + t * d[1]], abs=1e-8)
