"""build_geometry's matching, reconstruction and checks, and register_against, on synthetic
scenes with exact keypoints: a nadir survey over hills and buildings, and a street walk."""

from __future__ import annotations

import numpy as np
import pytest

import vloc.workers.core.geometry as geometry_package
from tests.core.geometry.scene import (
    F_TRUE,
    GROUND_ALT,
    HEIGHT,
    K_TRUE,
    WIDTH,
    level_rotation,
    observe,
    rotation_angle_deg,
    street,
    survey,
    tilted_rotation,
)
from vloc.workers.core.geometry import build_geometry, register_against, tie_pairs, tie_reach
from vloc.workers.core.geometry import pairs as pairs_module
from vloc.workers.core.geometry.camera import compass_heading_deg
from vloc.workers.core.geometry.models import Structure


def _build(s, *, gps_sigma=0.0, seed=0, **kwargs):
    rng = np.random.default_rng(seed)
    gps = s.positions + rng.normal(0.0, gps_sigma, s.positions.shape)
    return build_geometry(s.keypoints, s.image_descriptors, gps, s.altitudes, F_TRUE,
                          seed=seed, **kwargs)


def _with_points(s, built):
    """The geometry with every keypoint's 3-D point, as the map build gives it
    (:func:`workers.core.mapbuild.map_geometry`)."""
    geo, st = built
    offsets = np.concatenate([[0], np.cumsum([len(k) for k in s.keypoints])])
    seen = [(s.keypoints[i][st.observations[i], :2], st.points[i]) for i in range(len(s))]
    geo.add_points("sift", np.concatenate(s.keypoints), offsets, seen)
    return geo, offsets


@pytest.fixture(scope="module")
def surveyed():
    s = survey(np.random.default_rng(10), max_tilt_deg=10.0)
    built = _build(s, gps_sigma=0.3)
    assert built is not None
    geo, offsets = _with_points(s, built)
    return s, geo, offsets


@pytest.fixture(scope="module")
def walked():
    s = street(np.random.default_rng(11), n_points=2000)
    built = _build(s)
    assert built is not None
    geo, offsets = _with_points(s, built)
    return s, geo, offsets


def test_build_geometry_of_a_survey(surveyed):
    s, geo, _ = surveyed
    assert geo.reconstructed.all()
    assert geo.residual_px < 0.01 and geo.gps_rms < 0.5 and geo.models == 1
    assert geo.intrinsics.f == pytest.approx(F_TRUE, rel=1e-3)
    assert np.linalg.norm(geo.centres - s.centres, axis=1).max() < 0.5
    assert max(rotation_angle_deg(a, b)
               for a, b in zip(geo.rotations, s.rotations, strict=True)) < 0.5
    # every keypoint's 3-D point: most on their true points, the rest interpolated
    points = np.asarray(geo.points["sift"])
    assert points.shape == (sum(len(k) for k in s.keypoints), 3)
    err = np.linalg.norm(points - s.points[np.concatenate(s.point_ids)], axis=1)
    # (a keypoint no other image sees has no tie point near: 14 % here)
    assert np.isfinite(err).mean() > 0.8
    assert np.nanmedian(err) < 1.0
    lo, hi = geo.altitude_range()
    assert lo < s.centres[:, 2].min() and hi > s.centres[:, 2].max()
    direction, sigma = geo.view_prior()
    assert direction[2] < -0.98 and sigma >= 5.0


def test_build_geometry_of_a_street_walk(walked):
    s, geo, _ = walked
    assert geo.reconstructed.all() and geo.residual_px < 0.1
    assert np.linalg.norm(geo.centres - s.centres, axis=1).max() < 0.1
    assert geo.intrinsics.f == pytest.approx(F_TRUE, rel=1e-3)
    # the cameras 1.6 m above the road, the facades' points where they stand
    np.testing.assert_allclose(geo.centres[:, 2], s.centres[:, 2], atol=0.05)
    points = np.asarray(geo.points["sift"])
    err = np.linalg.norm(points - s.points[np.concatenate(s.point_ids)], axis=1)
    assert np.isfinite(err).mean() > 0.95 and np.nanmedian(err) < 0.5


def test_build_geometry_needs_three_images():
    s = survey(np.random.default_rng(0), rows=1, cols=3)
    for n in (0, 1, 2):
        assert build_geometry(s.keypoints[:n], s.image_descriptors[:n], s.positions[:n],
                              s.altitudes[:n], F_TRUE) is None
    assert tie_pairs(s.positions[:2]) == []


def test_build_geometry_of_unrelated_images_is_none():
    rng = np.random.default_rng(1)
    s = survey(rng, rows=1, cols=4)
    desc = [rng.integers(0, 256, d.shape, dtype=np.uint8) for d in s.image_descriptors]
    assert build_geometry(s.keypoints, desc, s.positions, s.altitudes, F_TRUE) is None
    assert _build(s) is not None  # the descriptors, not the scene, say no


def _structure(n, *, placed, residual_px=0.5, gps_rms_h=1.0):
    centres = np.full((n, 3), np.nan)
    centres[:placed] = [0.0, 0.0, 100.0]
    rotations = np.full((n, 3, 3), np.nan)
    rotations[:placed] = np.eye(3)
    return Structure(rotations, centres, K_TRUE, 0.0, [np.zeros(0, np.int64)] * n,
                     [np.zeros((0, 3))] * n, residual_px=residual_px, gps_rms_h=gps_rms_h,
                     gps_rms_v=2.0, models=1)


@pytest.mark.parametrize(("kwargs", "kept"), [
    (dict(placed=10), True),
    (dict(placed=3), True),                       # 30 % of the images: enough
    (dict(placed=2), False),                      # 20 %: too few
    (dict(placed=10, residual_px=1.9), True),
    (dict(placed=10, residual_px=4.5), False),    # points that do not reproject
    (dict(placed=10, gps_rms_h=14.0), True),
    (dict(placed=10, gps_rms_h=16.0), False),     # cameras far from their tags
])
def test_build_geometry_refuses_a_structure_that_fails_its_checks(monkeypatch, kwargs, kept):
    s = survey(np.random.default_rng(2), rows=2, cols=5)
    monkeypatch.setattr(geometry_package, "match_pairs", lambda *a, **k: [])
    monkeypatch.setattr(geometry_package, "reconstruct",
                        lambda *a, **k: _structure(len(s), **kwargs))
    built = _build(s)
    assert (built is not None) is kept
    if kept:
        geo, st = built
        assert geo.reconstructed.sum() == kwargs["placed"] and geo.points == {}
        assert (geo.residual_px, geo.gps_rms) == (st.residual_px, st.gps_rms_h)
    monkeypatch.setattr(geometry_package, "reconstruct", lambda *a, **k: None)
    assert _build(s) is None


def test_known_pairs_are_not_matched_again(monkeypatch):
    s = survey(np.random.default_rng(3), rows=2, cols=3)
    planned = tie_pairs(s.positions)
    assert planned and tie_reach(s.positions) == pytest.approx(
        6.0 * np.median([np.sort(np.linalg.norm(s.positions - p, axis=1))[1]
                         for p in s.positions]))
    known = {}
    for a, b in planned:
        known[(a, b)] = pairs_module.match_pair(a, b, s.keypoints[a], s.image_descriptors[a],
                                                s.keypoints[b], s.image_descriptors[b])
    matched = []
    real = pairs_module.match_pair
    monkeypatch.setattr(pairs_module, "match_pair",
                        lambda a, b, *args, **kw: matched.append((a, b)) or real(a, b, *args,
                                                                                  **kw))
    here = _build(s)
    assert sorted(matched) == planned
    matched.clear()
    apart = _build(s, known_pairs=known)
    assert matched == []
    np.testing.assert_array_equal(here[0].centres, apart[0].centres)
    np.testing.assert_array_equal(here[0].rotations, apart[0].rotations)


def _frame(s, R, C):
    """A new camera's keypoints and its matches to each map image that shares points."""
    kp, _, ids = observe(s.points, s.descriptors, R, C, K_TRUE, max_range=40.0
                         if C[2] < GROUND_ALT + 5 else np.inf)
    matches = []
    for i, map_ids in enumerate(s.point_ids):
        _, q, m = np.intersect1d(ids, map_ids, return_indices=True)
        if len(q) >= 8:
            matches.append((i, q, m))
    return kp, matches


def test_register_against_recovers_a_new_camera_over_the_survey(surveyed):
    s, geo, offsets = surveyed
    R = tilted_rotation(np.radians(70.0), 6.0, 0.4)
    C = np.array([30.0, 9.0, GROUND_ALT + 42.0])
    kp, matches = _frame(s, R, C)
    assert len(matches) >= 3
    rows = [(i, q, m + offsets[i]) for i, q, m in matches]
    reg = register_against(geo, "sift", kp, rows, frame_shape=(HEIGHT, WIDTH))
    assert reg is not None
    assert np.linalg.norm(reg.xy - C[:2]) < 0.5
    assert reg.height == pytest.approx(C[2], abs=0.5)
    assert abs((reg.heading_deg - compass_heading_deg(R) + 180) % 360 - 180) < 1.0
    assert set(reg.images) == {i for i, _, _ in matches}
    # map rows local to each image would place the frame on the wrong keypoints (but for
    # image 0's, whose rows start at 0)
    local = [(i, q, m) for i, q, m in matches if i != 0]
    wrong = register_against(geo, "sift", kp, local, frame_shape=(HEIGHT, WIDTH))
    assert wrong is None or np.linalg.norm(wrong.xy - C[:2]) > 5.0


def test_register_against_recovers_a_new_camera_on_the_street(walked):
    s, geo, offsets = walked
    R = level_rotation(np.radians(25.0), pitch_deg=3.0)
    C = np.array([7.7, 0.3, GROUND_ALT + 1.55])  # between the map's images
    kp, matches = _frame(s, R, C)
    rows = [(i, q, m + offsets[i]) for i, q, m in matches]
    reg = register_against(geo, "sift", kp, rows, frame_shape=(HEIGHT, WIDTH))
    assert reg is not None
    assert np.linalg.norm(reg.xy - C[:2]) < 0.5
    assert reg.height == pytest.approx(C[2], abs=0.5)


def test_register_against_a_larger_frame_keeps_the_principal_point(surveyed):
    # a 400x300 frame of the same camera: its principal point 40 and 30 px further in
    s, geo, offsets = surveyed
    R = tilted_rotation(np.radians(-20.0), 3.0, 1.0)
    C = np.array([20.0, 12.0, GROUND_ALT + 48.0])
    K = type(K_TRUE)(K_TRUE.f, K_TRUE.cx + 40.0, K_TRUE.cy + 30.0)
    kp, _, ids = observe(s.points, s.descriptors, R, C, K, size=(400, 300))
    rows = []
    for i, map_ids in enumerate(s.point_ids):
        _, q, m = np.intersect1d(ids, map_ids, return_indices=True)
        if len(q) >= 8:
            rows.append((i, q, m + offsets[i]))
    reg = register_against(geo, "sift", kp, rows, frame_shape=(300, 400))
    assert reg is not None and np.linalg.norm(reg.xy - C[:2]) < 1.0
    off = register_against(geo, "sift", kp, rows, frame_shape=(HEIGHT, WIDTH))
    assert off is None or np.linalg.norm(off.xy - C[:2]) > 5.0


def test_register_against_without_points_or_matches_is_none(surveyed):
    s, geo, offsets = surveyed
    kp, matches = _frame(s, tilted_rotation(0.0, 2.0, 0.0),
                         np.array([20.0, 10.0, GROUND_ALT + 50.0]))
    rows = [(i, q, m + offsets[i]) for i, q, m in matches]
    assert register_against(geo, "sift", kp, rows, frame_shape=(HEIGHT, WIDTH)) is not None
    assert register_against(geo, "orb", kp, rows, frame_shape=(HEIGHT, WIDTH)) is None
    assert register_against(geo, "sift", kp, [], frame_shape=(HEIGHT, WIDTH)) is None
