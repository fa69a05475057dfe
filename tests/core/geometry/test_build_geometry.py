"""build_geometry's checks and register_against, on synthetic surveys with exact keypoints."""

from __future__ import annotations

import numpy as np
import pytest

from tests.core.geometry.scene import (
    F_TRUE,
    HEIGHT,
    K_TRUE,
    WIDTH,
    observe,
    rotation_angle_deg,
    survey,
    tilted_rotation,
)
from vloc.workers.core.geometry import build_geometry, register_against
from vloc.workers.core.geometry.camera import Intrinsics, compass_heading_deg

K0 = Intrinsics.centred(F_TRUE, WIDTH, HEIGHT)


def _build(s, gps_sigma=0.3, seed=0):
    rng = np.random.default_rng(seed)
    gps = s.positions + rng.normal(0.0, gps_sigma, s.positions.shape)
    alt = s.altitudes + rng.normal(0.0, 0.2, len(gps))
    return build_geometry(s.keypoints, s.image_descriptors, gps, alt, K0, seed=seed)


@pytest.fixture(scope="module")
def surveyed():
    s = survey(np.random.default_rng(10), max_tilt_deg=10.0)
    geo = _build(s)
    offsets = np.concatenate([[0], np.cumsum([len(k) for k in s.keypoints])])
    geo.add_ground("sift", np.concatenate(s.keypoints), offsets)
    return s, geo, offsets


def test_build_geometry_of_a_survey(surveyed):
    s, geo, _ = surveyed
    assert geo.reconstructed.all()
    assert geo.residual_px < 1.0 and geo.gps_rms < 1.0
    assert np.linalg.norm(geo.centres[:, :2] - s.centres[:, :2], axis=1).max() < 1.0
    assert max(rotation_angle_deg(a, b)
               for a, b in zip(geo.rotations, s.rotations, strict=True)) < 0.5
    lo, hi = geo.height_range()
    assert lo < s.centres[:, 2].min() and hi > s.centres[:, 2].max()


@pytest.mark.parametrize("n", [0, 1, 2])
def test_build_geometry_needs_three_images(n):
    s = survey(np.random.default_rng(0), rows=1, cols=3)
    assert build_geometry(s.keypoints[:n], s.image_descriptors[:n], s.positions[:n],
                          s.altitudes[:n], K0) is None


def test_build_geometry_of_unrelated_images_is_none():
    rng = np.random.default_rng(1)
    s = survey(rng, rows=1, cols=4)
    desc = [rng.integers(0, 256, d.shape, dtype=np.uint8) for d in s.image_descriptors]
    assert build_geometry(s.keypoints, desc, s.positions, s.altitudes, K0) is None


def test_build_geometry_of_a_low_camera_is_none():
    # the same survey scaled down to 4 m above the ground: a robot, not an aircraft
    s = survey(np.random.default_rng(2), rows=1, height=4.0, spacing=1.44, max_tilt_deg=3.0)
    assert _build(s, gps_sigma=0.0) is None
    big = survey(np.random.default_rng(2), rows=1, height=50.0, spacing=18.0, max_tilt_deg=3.0)
    assert _build(big, gps_sigma=0.0) is not None  # the check, not the scene, says no


def test_build_geometry_whose_heights_its_altitudes_do_not_follow_is_none():
    # a street-level map passes for a low survey looking down, but its altitudes say
    # nothing of the heights it solves: here they scatter by a third of the height
    s = survey(np.random.default_rng(3), rows=2, max_tilt_deg=5.0)
    assert _build(s) is not None
    scattered = np.random.default_rng(4).normal(0.0, 0.35 * np.median(s.centres[:, 2]),
                                                len(s.altitudes))
    assert build_geometry(s.keypoints, s.image_descriptors, s.positions,
                          s.altitudes + scattered, K0) is None
    # without altitudes the check cannot say, and does not refuse
    assert build_geometry(s.keypoints, s.image_descriptors, s.positions,
                          np.full(len(s.altitudes), np.nan), K0) is not None


def _frame(s, R, C):
    kp, desc, ids = observe(s.points, s.descriptors, R, C, K_TRUE)
    matches = []
    for i, map_ids in enumerate(s.point_ids):
        common, q, m = np.intersect1d(ids, map_ids, return_indices=True)
        if len(common) >= 8:
            matches.append((i, q, m))
    return kp, matches


def test_register_against_recovers_a_new_camera(surveyed):
    s, geo, offsets = surveyed
    R = tilted_rotation(np.radians(70.0), 6.0, 0.4)
    C = np.array([30.0, 9.0, 42.0])
    kp, matches = _frame(s, R, C)
    assert len(matches) >= 3
    global_rows = [(i, q, m + offsets[i]) for i, q, m in matches]
    reg = register_against(geo, "sift", kp, global_rows, frame_shape=(HEIGHT, WIDTH))
    assert reg is not None
    assert np.linalg.norm(reg.xy - C[:2]) < 0.5
    assert reg.height == pytest.approx(C[2], rel=0.03)
    assert abs((reg.heading_deg - compass_heading_deg(R) + 180) % 360 - 180) < 1.0
    assert set(reg.images) == {i for i, _, _ in matches}
    # map rows local to each image would place the frame on the wrong keypoints
    wrong = register_against(geo, "sift", kp, matches, frame_shape=(HEIGHT, WIDTH))
    assert wrong is None or np.linalg.norm(wrong.xy - C[:2]) > 5.0


def test_register_against_without_ground_or_matches_is_none(surveyed):
    s, geo, offsets = surveyed
    kp, matches = _frame(s, tilted_rotation(0.0, 2.0, 0.0), np.array([20.0, 10.0, 50.0]))
    rows = [(i, q, m + offsets[i]) for i, q, m in matches]
    assert register_against(geo, "orb", kp, rows, frame_shape=(HEIGHT, WIDTH)) is None
    assert register_against(geo, "sift", kp, [], frame_shape=(HEIGHT, WIDTH)) is None
