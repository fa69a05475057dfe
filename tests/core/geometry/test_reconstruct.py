"""Plane bundle adjustment on a synthetic survey with exact tie points and noisy GPS."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.optimize import least_squares

from tests.core.geometry.scene import (
    F_TRUE,
    GROUND_ALT,
    HEIGHT,
    WIDTH,
    exact_pairs,
    rotation_angle_deg,
    survey,
    tilted_rotation,
)
from vloc.workers.core.geometry.camera import Intrinsics, backproject_to_ground
from vloc.workers.core.geometry.pairs import match_pairs
from vloc.workers.core.geometry.reconstruct import (
    BlockResult,
    _initial_headings,
    _transfer,
    _unrobust,
    adjust_block,
    block_key,
    block_pairs,
    ground_points,
    reconstruct_in_blocks,
    reconstruct_plane,
    spatial_blocks,
)


def _transfer_reference(Ra, Ca, Rb, Cb, f, c, p):
    """One pixel at a time: the ray of p from camera a meets Z = 0 at X, projected into b."""
    out = []
    for i in range(len(p)):
        d_cam = [(p[i][0] - c[0]) / f, (p[i][1] - c[1]) / f, 1.0]
        # camera -> world: the transpose of the world -> camera rotation
        d = [sum(Ra[i][r][k] * d_cam[r] for r in range(3)) for k in range(3)]
        t = -Ca[i][2] / d[2]
        X = [Ca[i][k] + t * d[k] for k in range(3)]
        x_cam = [sum(Rb[i][k][j] * (X[j] - Cb[i][j]) for j in range(3)) for k in range(3)]
        out.append([f * x_cam[0] / x_cam[2] + c[0], f * x_cam[1] / x_cam[2] + c[1]])
    return np.array(out)


def test_transfer_matches_slow_reference():
    rng = np.random.default_rng(3)
    n = 40
    Ra = np.stack([tilted_rotation(rng.uniform(-3, 3), rng.uniform(0, 20), rng.uniform(0, 6))
                   for _ in range(n)])
    Rb = np.stack([tilted_rotation(rng.uniform(-3, 3), rng.uniform(0, 20), rng.uniform(0, 6))
                   for _ in range(n)])
    Ca = np.column_stack([rng.uniform(-50, 50, (n, 2)), rng.uniform(20, 80, n)])
    Cb = Ca + np.column_stack([rng.uniform(-15, 15, (n, 2)), rng.uniform(-5, 5, n)])
    f, c = 280.0, np.array([160.0, 120.0])
    p = rng.uniform([0, 0], [320, 240], size=(n, 2))
    fast = _transfer(Ra, Ca, Rb, Cb, f, c, p)
    np.testing.assert_allclose(fast, _transfer_reference(Ra, Ca, Rb, Cb, f, c, p), atol=1e-8)


def test_transfer_through_identical_cameras_is_identity():
    R = np.stack([tilted_rotation(0.4, 7.0, 1.0)] * 5)
    C = np.tile([3.0, -2.0, 45.0], (5, 1))
    p = np.array([[0.0, 0.0], [160, 120], [319, 239], [10, 200], [300, 5]])
    np.testing.assert_allclose(_transfer(R, C, R, C, 250.0, np.array([160.0, 120.0]), p), p,
                               atol=1e-9)


def _soft_l1(z):
    """scipy's soft-L1 loss rho(z) = 2 (sqrt(1 + z) - 1) of a squared, scaled residual z."""
    return 2.0 * (np.sqrt(1.0 + z) - 1.0)


@pytest.mark.parametrize("scale", [0.5, 2.0, 7.0])
def test_unrobust_soft_l1_cost_equals_squared_cost(scale):
    r = np.concatenate([np.linspace(-1e3, 1e3, 201), [0.0, 1e-6, -1e-6, scale, -scale]])
    u = _unrobust(r, scale)
    # least_squares's cost of residual u under soft-L1 with f_scale: 0.5 s^2 rho((u/s)^2)
    np.testing.assert_allclose(scale**2 * _soft_l1((u / scale) ** 2), r**2, rtol=1e-10,
                               atol=1e-12)
    assert (np.sign(u) == np.sign(r)).all()


def test_unrobust_makes_soft_l1_fit_an_ordinary_least_squares_fit():
    # A line through points with two gross outliers: soft-L1 on the plain residuals resists
    # them, soft-L1 on unrobust residuals must give the ordinary least-squares line.
    rng = np.random.default_rng(0)
    x = np.linspace(0, 10, 30)
    y = 2.0 * x + 1.0 + rng.normal(0, 0.1, x.size)
    y[[4, 20]] += [40.0, -35.0]
    A = np.column_stack([x, np.ones_like(x)])
    ols, *_ = np.linalg.lstsq(A, y, rcond=None)
    sol = least_squares(lambda p: _unrobust(A @ p - y, 1.0), [0.0, 0.0], loss="soft_l1",
                        f_scale=1.0, xtol=1e-12, ftol=1e-12, gtol=1e-12)
    np.testing.assert_allclose(sol.x, ols, rtol=1e-4)
    assert sol.cost == pytest.approx(0.5 * np.sum((A @ ols - y) ** 2), rel=1e-8)
    robust = least_squares(lambda p: A @ p - y, [0.0, 0.0], loss="soft_l1", f_scale=1.0)
    assert abs(robust.x[0] - ols[0]) > 0.1  # so the comparison above can tell them apart


@pytest.mark.parametrize("headings", ["lines", "random"])
def test_initial_headings_of_nadir_survey(headings):
    rng = np.random.default_rng(5)
    s = survey(rng, max_tilt_deg=0.0, headings=headings)
    s.centres[:, 2] = 50.0  # one height: the initial guess is a common one
    pairs = exact_pairs(s, rng)
    theta, height = _initial_headings(pairs, s.positions, s.K, len(s.centres))
    truth = np.array([math.atan2(R[0, 1], R[0, 0]) for R in s.rotations])
    np.testing.assert_allclose(np.angle(np.exp(1j * (theta - truth))), 0.0, atol=1e-6)
    assert height == pytest.approx(50.0, rel=1e-6)


def _survey_problem(seed, *, max_tilt_deg, headings="lines", gps_sigma=0.3, alt_sigma=0.2):
    rng = np.random.default_rng(seed)
    s = survey(rng, max_tilt_deg=max_tilt_deg, headings=headings)
    pairs = exact_pairs(s, rng)
    gps = s.positions + rng.normal(0.0, gps_sigma, s.positions.shape)
    alt = s.altitudes + rng.normal(0.0, alt_sigma, len(gps))
    return s, pairs, gps, alt


def _rotation_errors(rec, s):
    return [rotation_angle_deg(a, b) for a, b in zip(rec.rotations, s.rotations, strict=True)]


@pytest.mark.parametrize("seed", [0, 3])
def test_reconstruct_plane_recovers_tilted_survey(seed):
    # Survey lines, tilts up to 10 degrees, the focal length known (EXIF).
    s, pairs, gps, alt = _survey_problem(seed, max_tilt_deg=10.0)
    rec = reconstruct_plane(pairs, gps, alt, Intrinsics.centred(F_TRUE, WIDTH, HEIGHT))
    assert rec.reconstructed.all()
    assert np.linalg.norm(rec.centres - s.centres, axis=1).max() < 1.0
    assert max(_rotation_errors(rec, s)) < 0.5
    assert rec.intrinsics.f == pytest.approx(F_TRUE, rel=0.02)
    assert (rec.intrinsics.cx, rec.intrinsics.cy) == (WIDTH / 2, HEIGHT / 2)
    assert rec.ground_alt == pytest.approx(GROUND_ALT, abs=1.0)
    assert rec.residual_px < 0.1
    # The cameras sit at their true places, so their distance to the tags is the GPS noise.
    noise_rms = math.sqrt(np.mean(np.sum((gps - s.positions) ** 2, axis=1)))
    assert rec.gps_rms == pytest.approx(noise_rms, abs=0.15)


def test_reconstruct_plane_refines_a_wrong_focal_length_with_any_headings():
    # Every image at any heading, the focal length guessed 10 % long: perspective in the
    # tilted views pulls it most of the way back. Height follows the focal length (the
    # ground sampling distance height / f is what the pixels fix), so heights are within a
    # few per cent rather than sub-metre.
    s, pairs, gps, alt = _survey_problem(1, max_tilt_deg=10.0, headings="random")
    f0 = 1.1 * F_TRUE
    rec = reconstruct_plane(pairs, gps, alt, Intrinsics.centred(f0, WIDTH, HEIGHT))
    assert rec.reconstructed.all()
    assert abs(rec.intrinsics.f - F_TRUE) < 0.4 * (f0 - F_TRUE)
    assert np.linalg.norm(rec.centres[:, :2] - s.centres[:, :2], axis=1).max() < 1.0
    np.testing.assert_allclose(rec.centres[:, 2] / rec.intrinsics.f, s.centres[:, 2] / F_TRUE,
                               rtol=0.01)
    assert max(_rotation_errors(rec, s)) < 1.0
    assert rec.residual_px < 0.1 and rec.gps_rms < 1.0


def test_reconstruct_plane_near_nadir_fixes_pose_and_scale():
    # Near nadir only height / focal is observable (they trade off over flat ground): the
    # horizontal positions, rotations and ground sampling distance are what must be right.
    s, pairs, gps, alt = _survey_problem(2, max_tilt_deg=3.0, gps_sigma=0.5, alt_sigma=1.0)
    rec = reconstruct_plane(pairs, gps, alt, Intrinsics.centred(F_TRUE, WIDTH, HEIGHT))
    assert rec.reconstructed.all()
    assert np.linalg.norm(rec.centres[:, :2] - s.centres[:, :2], axis=1).max() < 1.0
    assert max(_rotation_errors(rec, s)) < 0.5
    gsd = rec.centres[:, 2] / rec.intrinsics.f
    np.testing.assert_allclose(gsd, s.centres[:, 2] / F_TRUE, rtol=0.01)
    assert rec.intrinsics.f == pytest.approx(F_TRUE, rel=0.1)
    assert rec.residual_px < 0.1
    assert rec.gps_rms < 1.0


def test_reconstruct_plane_without_pairs_reconstructs_nothing():
    rec = reconstruct_plane([], np.zeros((4, 2)), np.full(4, np.nan),
                            Intrinsics(250.0, 160.0, 120.0))
    assert not rec.reconstructed.any()
    assert np.isnan(rec.rotations).all() and np.isnan(rec.centres).all()
    assert math.isnan(rec.residual_px) and math.isnan(rec.gps_rms)


def test_unmatched_image_is_left_out_and_unknown_altitudes_are_fine():
    s, pairs, gps, _ = _survey_problem(3, max_tilt_deg=5.0)
    # a ninth image 500 m away matches nothing
    gps = np.vstack([gps, [500.0, 500.0]])
    rec = reconstruct_plane(pairs, gps, np.full(len(gps), np.nan),
                            Intrinsics.centred(F_TRUE, WIDTH, HEIGHT))
    assert rec.reconstructed.tolist() == [True] * len(s.centres) + [False]
    assert np.isnan(rec.rotations[-1]).all()
    assert np.linalg.norm(rec.centres[:-1, :2] - s.centres[:, :2], axis=1).max() < 1.0
    # Without altitudes the ground is the GPS altitude frame's zero.
    assert rec.ground_alt == pytest.approx(0.0)
    np.testing.assert_allclose(rec.centres[:-1, 2] / rec.intrinsics.f,
                               s.centres[:, 2] / F_TRUE, rtol=0.02)


def test_ground_points_places_keypoints_under_their_cameras():
    s, pairs, gps, alt = _survey_problem(0, max_tilt_deg=10.0)
    rec = reconstruct_plane(pairs, gps, alt, Intrinsics.centred(F_TRUE, WIDTH, HEIGHT))
    keypoints = s.keypoints + [np.zeros((3, 4), np.float32), np.zeros((0, 4), np.float32)]
    rows = np.concatenate([rec.rotations, np.full((2, 3, 3), np.nan)])
    cents = np.concatenate([rec.centres, np.full((2, 3), np.nan)])
    rec = type(rec)(rows, cents, rec.intrinsics, rec.ground_alt, rec.residual_px, rec.gps_rms)
    out = ground_points(rec, keypoints)
    assert [len(o) for o in out] == [len(k) for k in keypoints]
    for i in range(len(s.centres)):
        # the keypoints came from ground points: they go back there (to the reconstruction's
        # accuracy), and exactly where the reconstructed camera's rays meet the ground
        err = np.linalg.norm(out[i] - s.points[s.point_ids[i]], axis=1)
        assert np.median(err) < 0.5
        np.testing.assert_allclose(out[i], backproject_to_ground(
            rec.rotations[i], rec.centres[i], rec.intrinsics, keypoints[i][:, :2]))
    assert np.isnan(out[-2]).all() and out[-1].shape == (0, 2)


def test_match_pairs_finds_the_overlapping_images():
    rng = np.random.default_rng(4)
    s = survey(rng, max_tilt_deg=3.0)
    pairs = match_pairs(s.keypoints, s.image_descriptors, s.positions, max_distance=40.0)
    found = {(p.a, p.b) for p in pairs}
    n = len(s.centres)
    overlapping = {(a, b) for a in range(n) for b in range(a + 1, n)
                   if len(np.intersect1d(s.point_ids[a], s.point_ids[b])) >= 10
                   and np.linalg.norm(s.positions[a] - s.positions[b]) <= 40.0}
    assert found == overlapping and len(found) >= n
    for p in pairs:
        assert p.a < p.b and len(p.pa) == len(p.pb) == 30  # capped at max_per_pair
        # every tie point is one ground point seen by both: the homography maps it exactly
        ph = np.column_stack([p.pa, np.ones(len(p.pa))]) @ p.homography.T
        np.testing.assert_allclose(ph[:, :2] / ph[:, 2:], p.pb, atol=1e-2)
    # nothing further apart than max_distance is tried
    near = match_pairs(s.keypoints, s.image_descriptors, s.positions, max_distance=10.0)
    assert near == []


def test_match_pairs_of_unrelated_images_is_empty():
    rng = np.random.default_rng(1)
    kps = [rng.uniform(0, 300, (200, 4)).astype(np.float32) for _ in range(4)]
    desc = [rng.integers(0, 256, (200, 128), dtype=np.uint8) for _ in range(4)]
    pos = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [10.0, 10.0]])
    assert match_pairs(kps, desc, pos, max_distance=50.0) == []
    assert match_pairs(kps[:1], desc[:1], pos[:1], max_distance=50.0) == []



def test_spatial_blocks_are_compact_and_small_enough():
    rng = np.random.default_rng(2)
    positions = rng.uniform(0, 1000, (1000, 2))
    labels = spatial_blocks(positions, 90)
    counts = np.bincount(labels)
    assert counts.sum() == 1000 and counts.max() <= 90 and counts.min() >= 45
    # bisection: the blocks' bounding boxes do not overlap
    boxes = [(positions[labels == b].min(axis=0), positions[labels == b].max(axis=0))
             for b in range(len(counts))]
    for i, (lo_a, hi_a) in enumerate(boxes):
        for lo_b, hi_b in boxes[i + 1:]:
            assert (hi_a < lo_b).any() or (hi_b < lo_a).any()
    assert (spatial_blocks(positions, 1000) == 0).all()


def _gridded_survey(seed, max_tilt_deg, altitude_offset=None):
    """A 4 x 6 survey with exact tie points, GPS noise of 0.3 m and altitude noise of
    0.2 m (plus ``altitude_offset(gps)``): (survey, pairs, gps, altitudes)."""
    rng = np.random.default_rng(seed)
    s = survey(rng, rows=4, cols=6, max_tilt_deg=max_tilt_deg)
    pairs = exact_pairs(s, rng)
    gps = s.positions + rng.normal(0.0, 0.3, s.positions.shape)
    alt = s.altitudes + rng.normal(0.0, 0.2, len(gps))
    if altitude_offset is not None:
        alt = alt + altitude_offset(gps)
    return s, pairs, gps, alt


def test_reconstruct_in_blocks_matches_the_whole_adjustment():
    # 4 x 6 images cut into blocks of at most 8: every camera placed as the whole
    # adjustment places it, the map's focal length and ground as well.
    s, pairs, gps, alt = _gridded_survey(6, 8.0)
    K0 = Intrinsics.centred(F_TRUE, WIDTH, HEIGHT)
    blocks = reconstruct_in_blocks(pairs, gps, alt, K0, max_block=8)
    assert len(np.unique(spatial_blocks(gps, 8))) >= 3
    assert blocks.reconstructed.all()
    assert np.linalg.norm(blocks.centres - s.centres, axis=1).max() < 1.5  # 8-image blocks
    assert max(_rotation_errors(blocks, s)) < 0.5
    assert blocks.intrinsics.f == pytest.approx(F_TRUE, rel=0.02)
    assert blocks.ground_alt == pytest.approx(GROUND_ALT, abs=1.0)
    # the residual is the tie points' with the map's one focal length, not each block's own
    assert blocks.residual_px < 0.2 and blocks.gps_rms < 1.0
    whole = reconstruct_in_blocks(pairs, gps, alt, K0, max_block=len(gps))
    np.testing.assert_allclose(blocks.centres, whole.centres, atol=1.5)


def _blocks_of(pairs, gps, alt, K0, max_block):
    return [(inside, adjust_block(inside, gps, alt, K0))
            for inside in block_pairs(pairs, gps, max_block)]


def test_blocks_of_other_focal_lengths_are_brought_to_the_maps():
    # Over flat ground a block fixes only height over focal: one block that settled on a
    # focal length 1.4 times the others', with heights and ground to match (as blocks of a
    # large survey do), is scaled back to the map's focal length before it is merged.
    s, pairs, gps, alt = _gridded_survey(7, 2.0)
    K0 = Intrinsics.centred(F_TRUE, WIDTH, HEIGHT)
    blocks = _blocks_of(pairs, gps, alt, K0, 8)
    assert len(blocks) >= 3
    inside, res = blocks[1]
    h = res.centres[:, 2]
    stretched = BlockResult(res.cameras, res.rotations, np.column_stack([res.centres[:, :2], 1.4 * h]),
                            1.4 * res.focal, res.ground_alt - 0.4 * float(np.median(h)),
                            res.residual_px, res.gps_rms)
    known = {block_key(i, gps, alt, K0): r for i, r in blocks}
    known[block_key(inside, gps, alt, K0)] = stretched
    rec = reconstruct_in_blocks(pairs, gps, alt, K0, max_block=8, known=known)
    assert rec.intrinsics.f == pytest.approx(F_TRUE, rel=0.02)
    # the stretched block's heights are the survey's again (merged as they came, they
    # would be 20 m too high), and its ground is the others'
    np.testing.assert_allclose(rec.centres[:, 2], s.centres[:, 2], atol=1.0)
    assert np.ptp(rec.camera_ground_alt) < 1.0
    assert rec.ground_alt == pytest.approx(GROUND_ALT, abs=1.0)
    assert rec.residual_px < 0.2
    assert np.abs(rec.height_offsets(alt)).max() < 1.0


def test_blocks_over_grounds_at_other_altitudes_keep_their_own():
    # The east half of the survey flown over ground 20 m higher (its GPS altitudes 20 m
    # up): each block's heights are measured from its own ground.
    def east_of_middle(gps):
        return gps[:, 0] > np.median(gps[:, 0])

    s, pairs, gps, alt = _gridded_survey(8, 2.0, lambda gps: 20.0 * east_of_middle(gps))
    east = east_of_middle(gps)
    K0 = Intrinsics.centred(F_TRUE, WIDTH, HEIGHT)
    rec = reconstruct_in_blocks(pairs, gps, alt, K0, max_block=12)
    assert rec.reconstructed.all()
    np.testing.assert_allclose(rec.centres[:, 2], s.centres[:, 2], atol=1.0)
    np.testing.assert_allclose(rec.camera_ground_alt[east], GROUND_ALT + 20.0, atol=1.0)
    np.testing.assert_allclose(rec.camera_ground_alt[~east], GROUND_ALT, atol=1.0)
    assert np.abs(rec.height_offsets(alt)).max() < 1.0
    # against one ground for the whole map the east half would be 10 m off either way
    assert np.std(rec.centres[:, 2] - (alt - rec.ground_alt)) > 9.0
