"""Bringing a reconstruction onto GPS: Umeyama's closed form and the robust, weighted fit."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tests.core.geometry.scene import rotation_angle_deg, tilted_rotation
from vloc.workers.core.geometry.align import Similarity, align_to_gps, umeyama

TRUTH = Similarity(0.2, Rotation.from_rotvec([0.3, -0.5, 1.2]).as_matrix(),
                   np.array([10.0, 20.0, 30.0]))
"""Reconstruction -> map: a model built at five times the map's scale, turned and shifted."""


def test_umeyama_known_answer_by_hand():
    # a right triangle and a fourth point, turned 90 degrees about the vertical, doubled
    # and shifted: (x, y, z) -> 2 (-y, x, z) + (1, 2, 3)
    src = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    dst = np.array([[1.0, 2.0, 3.0], [1.0, 4.0, 3.0], [-1.0, 2.0, 3.0], [1.0, 2.0, 5.0]])
    sim = umeyama(src, dst)
    assert sim.scale == pytest.approx(2.0, abs=1e-12)
    np.testing.assert_allclose(sim.rotation, [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(sim.shift, [1, 2, 3], atol=1e-12)
    np.testing.assert_allclose(sim.apply(src), dst, atol=1e-12)


def test_umeyama_recovers_a_similarity_and_never_a_reflection():
    rng = np.random.default_rng(0)
    src = rng.normal(0.0, 50.0, (20, 3))
    sim = umeyama(src, TRUTH.apply(src))
    assert sim.scale == pytest.approx(TRUTH.scale, rel=1e-12)
    np.testing.assert_allclose(sim.rotation, TRUTH.rotation, atol=1e-12)
    np.testing.assert_allclose(sim.shift, TRUTH.shift, atol=1e-9)
    # a mirror image has no similarity onto it: the best proper rotation, not the mirror
    mirrored = src * [1.0, 1.0, -1.0]
    best = umeyama(src, mirrored)
    assert np.linalg.det(best.rotation) == pytest.approx(1.0)
    assert np.abs(best.apply(src) - mirrored).max() > 10.0


@pytest.mark.parametrize("src", [
    np.zeros((0, 3)),
    np.array([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0]]),                      # two points
    np.array([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0], [2.0, 4.0, 6.0], [-3.0, -6.0, -9.0]]),
    np.ones((5, 3)),                                                    # one point, repeated
], ids=["none", "two", "collinear", "coincident"])
def test_umeyama_of_a_degenerate_set_is_none(src):
    assert umeyama(src, src + 1.0) is None


def _cameras(rng, n=30, *, extent=(200.0, 150.0)):
    """``n`` nadir cameras with any heading that do not roll, over an ``extent`` (m) area:
    their map centres, and their centres and right axes in the reconstruction's frame."""
    centres = np.column_stack([rng.uniform(0, extent[0], n), rng.uniform(0, extent[1], n),
                               300.0 + rng.normal(0.0, 2.0, n)])
    rotations = np.stack([tilted_rotation(rng.uniform(-np.pi, np.pi), rng.uniform(0.0, 5.0),
                                          np.pi * rng.integers(0, 2)) for _ in range(n)])
    rec = (centres - TRUTH.shift) @ TRUTH.rotation / TRUTH.scale
    right = rotations[:, 0, :] @ TRUTH.rotation  # each row: R_truth^T x
    return centres, rec, right


def _close_to_truth(sim, *, scale=0.01, degrees=1.0):
    assert sim.scale == pytest.approx(TRUTH.scale, rel=scale)
    assert rotation_angle_deg(sim.rotation, TRUTH.rotation) < degrees


def _rms_h(err):
    return float(np.sqrt(np.mean(np.sum(err[:, :2] ** 2, axis=1))))


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_align_to_gps_recovers_a_known_similarity_through_gps_noise(seed):
    rng = np.random.default_rng(seed)
    centres, rec, right = _cameras(rng)
    gps = centres + rng.normal(0.0, [2.0, 2.0, 6.0], centres.shape)
    sim, inliers = align_to_gps(rec, right, gps, rng=np.random.default_rng(0))
    assert inliers.all()
    _close_to_truth(sim)
    err = sim.apply(rec) - centres
    # the slow obvious reference, least squares over the tags alone (Umeyama): as good
    # horizontally, where the tags are good; the level cameras make it better vertically
    ref = umeyama(rec, gps).apply(rec) - centres
    assert _rms_h(err) < min(1.0, 1.1 * _rms_h(ref))
    assert np.abs(err[:, 2]).max() < 0.6 * np.abs(ref[:, 2]).max()
    # exact tags, cameras exactly level: the similarity itself
    exact, _ = align_to_gps(rec, right, centres, rng=np.random.default_rng(0))
    np.testing.assert_allclose(exact.apply(rec), centres, atol=1e-3)


def test_align_to_gps_flags_a_camera_placed_100_m_off_and_keeps_the_fit():
    rng = np.random.default_rng(2)
    centres, rec, right = _cameras(rng)
    gps = centres + rng.normal(0.0, [2.0, 2.0, 6.0], centres.shape)
    bad = rec.copy()
    bad[7] += np.array([100.0, 0.0, 0.0]) @ TRUTH.rotation / TRUTH.scale  # 100 m east
    sim, inliers = align_to_gps(bad, right, gps, rng=np.random.default_rng(0))
    assert inliers.tolist() == [i != 7 for i in range(len(rec))]
    _close_to_truth(sim)
    # the slow obvious reference: Umeyama over every camera is pulled metres away
    pulled = umeyama(bad, gps)
    keep = np.arange(len(rec)) != 7
    assert np.abs(pulled.apply(rec[keep]) - centres[keep]).max() > 3.0
    assert np.abs(sim.apply(rec[keep]) - centres[keep]).max() < 1.5


def test_align_to_gps_leaves_unknown_altitudes_to_the_others():
    rng = np.random.default_rng(3)
    centres, rec, right = _cameras(rng)
    gps = centres.copy()
    gps[::3, 2] = np.nan
    sim, inliers = align_to_gps(rec, right, gps, rng=np.random.default_rng(0))
    assert inliers.all()
    np.testing.assert_allclose(sim.apply(rec), centres, atol=1e-3)
    # no altitude at all: horizontally right, level, at an altitude nothing says
    gps[:, 2] = np.nan
    sim, inliers = align_to_gps(rec, right, gps, rng=np.random.default_rng(0))
    assert inliers.all()
    placed = sim.apply(rec)
    np.testing.assert_allclose(placed[:, :2], centres[:, :2], atol=0.05)
    dz = placed[:, 2] - centres[:, 2]
    assert np.ptp(dz) < 0.2


def test_align_to_gps_keeps_a_model_near_level_when_the_gps_altitudes_drift():
    """A flight whose GPS altitude drifts by 100 m from first image to last (a nadir survey
    seen drifting 317 -> 431 m), over 100 x 75 m: fitted to its tags alone the model tilts
    45 degrees to follow the drift; the cameras' level right axes hold it within 3 (the
    drift is weighed as noise, so it still pulls: 2 degrees here, 5 over 200 m)."""
    rng = np.random.default_rng(4)
    centres, rec, right = _cameras(rng, extent=(100.0, 75.0))
    order = np.argsort(centres[:, 0])  # flown west to east
    drift = np.empty(len(rec))
    drift[order] = np.linspace(0.0, 100.0, len(rec))
    gps = centres + np.column_stack([np.zeros((len(rec), 2)), drift])
    sim, inliers = align_to_gps(rec, right, gps, rng=np.random.default_rng(0))
    assert rotation_angle_deg(sim.rotation, TRUTH.rotation) < 3.0
    assert sim.scale == pytest.approx(TRUTH.scale, rel=0.01)
    placed = sim.apply(rec)
    assert _rms_h(placed - centres) < 1.0
    # the drift only lifts it: by about its middle
    assert np.median(placed[:, 2] - centres[:, 2]) == pytest.approx(50.0, abs=5.0)
    tilted = umeyama(rec, gps)
    assert rotation_angle_deg(tilted.rotation, TRUTH.rotation) > 30.0
    # the cameras left out are those whose tags are furthest from the model
    off = np.abs(placed[:, 2] - gps[:, 2])
    assert inliers.sum() >= 0.8 * len(rec)
    assert (~inliers).sum() == 0 or off[~inliers].min() > off[inliers].max()


def test_align_to_gps_needs_three_cameras():
    rng = np.random.default_rng(5)
    centres, rec, right = _cameras(rng, n=3)
    assert align_to_gps(rec[:2], right[:2], centres[:2], rng=rng) is None
    sim, inliers = align_to_gps(rec, right, centres, rng=rng)
    assert inliers.all() and math.isclose(sim.scale, TRUTH.scale, rel_tol=1e-6)


def test_a_straight_line_of_cameras_is_aligned_by_their_level_rows():
    """A straight street or a single flight line: the centres leave the rotation about the
    line open, the cameras' level rows (across the line here) close it."""
    from scipy.spatial.transform import Rotation

    gps = np.column_stack([np.arange(0.0, 100.0, 10.0), np.zeros(10), np.full(10, 300.0)])
    rot = Rotation.from_rotvec([0.3, -0.5, 1.2]).as_matrix()
    rec = (gps - [10.0, 20.0, 30.0]) @ rot / 0.2  # the model: turned, shifted, x5
    right = np.tile([0.0, -1.0, 0.0], (10, 1)) @ rot  # image rows across the line
    sim, inliers = align_to_gps(rec, right, gps, rng=np.random.default_rng(0))
    assert inliers.all()
    np.testing.assert_allclose(sim.apply(rec), gps, atol=0.01)
    # the rows level: the model turned right about the line, or half a turn further (which
    # rows alone cannot tell; the cameras' axes do: the next test)
    np.testing.assert_allclose((right @ sim.rotation.T)[:, 2], 0.0, atol=1e-3)


def test_a_line_of_cameras_comes_out_upright():
    """Upside down, a street walk keeps every row level and every centre on its tag: the
    cameras' images pointing down (not up) choose between the two."""
    from scipy.spatial.transform import Rotation

    n = 8
    gps = np.column_stack([np.zeros(n), np.arange(n) * 1.5, np.full(n, 1.6)])
    # walking north, looking north-east and 5 degrees down: image rows level, image down
    # pointing mostly down
    look = np.radians(45.0)
    z = np.array([np.sin(look) * np.cos(0.087), np.cos(look) * np.cos(0.087), -0.087])
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R_world = np.stack([x, y, z])  # rows: the camera's axes in the world
    assert y[2] < -0.9
    for seed in range(4):
        rot = Rotation.from_rotvec(np.random.default_rng(seed).normal(0, 1, 3)).as_matrix()
        rec = gps @ rot * 3.0 + 7.0
        axes = np.stack([R_world @ rot] * n)
        sim, _ = align_to_gps(rec, axes[:, 0, :], gps, axes=axes,
                              rng=np.random.default_rng(seed))
        world = sim.apply_to_rotations(axes)
        assert (world[:, 1, 2] < -0.9).all(), seed  # the image's down points down
        np.testing.assert_allclose(sim.apply(rec), gps, atol=0.01)


def test_drifting_altitudes_do_not_tilt_a_lawnmower_survey():
    """GPS altitudes drifting 100 m over the flight: with the capture times the drift is
    told from a tilt (the legs run back and forth in time), and the model stays level."""
    rows, cols = 4, 6
    xy = np.array([[c * 20.0 if r % 2 == 0 else (cols - 1 - c) * 20.0, r * 30.0]
                   for r in range(rows) for c in range(cols)])
    truth = np.column_stack([xy, np.full(len(xy), 400.0)])
    times = 4.0 * np.arange(len(xy))
    gps = truth.copy()
    gps[:, 2] += 100.0 * times / times[-1]
    right = np.tile([1.0, 0.0, 0.0], (len(xy), 1))  # rows along the legs: no help across
    rec = truth * 0.5 + 3.0
    rng = np.random.default_rng(1)
    with_times, _ = align_to_gps(rec, right, gps, times=times, rng=rng)
    np.testing.assert_allclose(with_times.apply(rec)[:, 2] - 400.0,
                               np.full(len(xy), with_times.apply(rec)[0, 2] - 400.0),
                               atol=0.5)  # level (a constant offset is the drift's start)
    without, _ = align_to_gps(rec, right, gps, rng=np.random.default_rng(1))
    assert np.ptp(without.apply(rec)[:, 2]) > 30.0  # the drift tilts a model without times
