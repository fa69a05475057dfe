"""The particle filter against known distributions and known answers."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from workers.core.pf.config import CONFIGS, FilterConfig, config_from_params
from workers.core.pf.filter import GLOBAL, SIFT, ParticleFilter, cloud_stats
from workers.core.pf.measurement import distance_factor, log_likelihoods, normalise_log
from workers.core.pf.motion import MotionModel
from workers.core.pf.resampling import multinomial, systematic

# -- resampling --------------------------------------------------------------------------


@pytest.mark.parametrize("resample", [multinomial, systematic])
def test_resampler_draws_in_proportion_to_weights(resample):
    rng = np.random.default_rng(1)
    w = np.array([0.5, 0.0, 0.3, 0.2])
    counts = np.zeros(4)
    for _ in range(2000):
        counts += np.bincount(resample(w, rng), minlength=4)
    share = counts / counts.sum()
    np.testing.assert_allclose(share, w, atol=0.01)
    assert counts[1] == 0  # a zero-weight particle is never drawn


def test_systematic_is_within_one_of_expected_count():
    rng = np.random.default_rng(2)
    w = rng.random(50)
    w /= w.sum()
    for _ in range(20):
        counts = np.bincount(systematic(w, rng), minlength=50)
        assert np.all(np.abs(counts - 50 * w) < 1.0 + 1e-9)


def test_resampler_degenerate_weight_picks_one_particle():
    w = np.zeros(10)
    w[7] = 1.0
    assert set(multinomial(w, np.random.default_rng(0))) == {7}


# -- measurement -------------------------------------------------------------------------


def test_log_likelihood_matches_direct_formula():
    s = np.array([0.9, 0.5, 0.0, 1.0])
    d = np.array([0.0, 1.0, 2.0, 3.0])
    got = normalise_log(log_likelihoods(s, d, power=20.0, scale=2.0))
    direct = s**20 * distance_factor(d, 2.0)
    np.testing.assert_allclose(got, direct / direct.sum(), rtol=1e-12)
    assert got[2] == 0.0


def test_normalise_log_all_zero_weights_is_none():
    assert normalise_log(np.full(3, -np.inf)) is None


def test_power_20_survives_tiny_similarities():
    # 1e-30 ** 20 underflows in floating point; in the log domain the ranking survives.
    s = np.array([1e-30, 2e-30])
    w = normalise_log(log_likelihoods(s, np.zeros(2), power=20.0, scale=1.0))
    np.testing.assert_allclose(w, [1 / (1 + 2**20), 2**20 / (1 + 2**20)])


# -- cloud statistics --------------------------------------------------------------------


def test_cloud_stats_against_eq2_by_hand():
    xy = np.array([[0.0, 0.0], [2.0, 0.0], [4.0, 6.0]])
    w = np.array([0.25, 0.25, 0.5])
    st = cloud_stats(xy, w)
    mu_x, mu_y = 0.25 * 0 + 0.25 * 2 + 0.5 * 4, 0.5 * 6
    sx = np.sqrt(0.25 * (0 - mu_x) ** 2 + 0.25 * (2 - mu_x) ** 2 + 0.5 * (4 - mu_x) ** 2)
    sy = np.sqrt(0.25 * mu_y**2 + 0.25 * mu_y**2 + 0.5 * (6 - mu_y) ** 2)
    np.testing.assert_allclose(st.mean, [mu_x, mu_y])
    assert st.sigma_x == pytest.approx(sx)
    assert st.sigma_y == pytest.approx(sy)
    np.testing.assert_allclose(st.cov, np.cov(xy.T, aweights=w, ddof=0))


# -- motion ------------------------------------------------------------------------------


def test_motion_sigma_scales_with_time_and_speed():
    robot = MotionModel(sigma_floor=4.0, speed=0.6)
    uav = MotionModel(sigma_floor=4.0, speed=7.0)
    assert robot.sigma(1.0) == pytest.approx(np.hypot(4.0, 0.6))
    assert uav.sigma(5.0) == pytest.approx(np.hypot(4.0, 35.0))
    assert MotionModel(sigma_floor=4.0).sigma(5.0) == 4.0  # no speed: per-frame sigma
    assert uav.sigma(None) == pytest.approx(np.hypot(4.0, 7.0))  # nominal 1 s


def test_motion_pull_moves_a_fifth_towards_nearest_image():
    map_xy = np.array([[0.0, 0.0], [100.0, 0.0]])
    model = MotionModel(sigma_floor=1e-9, pull=0.2)
    xy = np.array([[10.0, 0.0], [90.0, 10.0]])
    moved, _ = model.move(xy, None, None, cKDTree(map_xy), map_xy, np.random.default_rng(0))
    np.testing.assert_allclose(moved, [[8.0, 0.0], [92.0, 8.0]], atol=1e-6)


def test_motion_noise_has_the_configured_spread():
    map_xy = np.zeros((1, 2))
    model = MotionModel(sigma_floor=4.0, pull=0.0)
    xy = np.zeros((20000, 2))
    moved, _ = model.move(xy, None, None, cKDTree(map_xy), map_xy, np.random.default_rng(3))
    assert moved.std(axis=0) == pytest.approx([4.0, 4.0], rel=0.03)


# -- the filter on a perfect similarity ----------------------------------------------------


def _route(n=120, spacing=2.0):
    """A rectangle-ish closed route of map images."""
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.stack([60 * np.cos(t), 30 * np.sin(t)], axis=1)


def _perfect(map_xy, truth, width=3.0):
    def sim(idx):
        d = np.linalg.norm(map_xy[idx] - truth, axis=1)
        return np.exp(-0.5 * (d / width) ** 2)
    return sim


@pytest.mark.parametrize("config", ["weiss2008", "default"])
def test_filter_with_perfect_similarity_converges_to_truth(config):
    map_xy = _route()
    cfg = CONFIGS[config]
    pf = ParticleFilter(map_xy, cKDTree(map_xy), cfg,
                        MotionModel(sigma_floor=2.0, speed=1.0, velocity=cfg.velocity),
                        2.0, np.random.default_rng(5))
    errors = []
    for k in range(40):
        truth = map_xy[(10 + k) % len(map_xy)]
        stats, used, _, _ = pf.step(_perfect(map_xy, truth), 1.0)
        errors.append(np.linalg.norm(stats.mean - truth))
    assert np.mean(errors[-20:]) < 3.0


def test_hybrid_switch_follows_thresholds():
    map_xy = _route()
    cfg = FilterConfig(speed=None)
    pf = ParticleFilter(map_xy, cKDTree(map_xy), cfg, MotionModel(sigma_floor=4.0), 2.0,
                        np.random.default_rng(0))
    assert pf.mode == SIFT  # IV-B: the first step is SIFT
    truth = map_xy[0]
    modes = []
    for _ in range(15):
        stats, used, _, _ = pf.step(_perfect(map_xy, truth, 2.0), None)
        spread = max(stats.sigma_x, stats.sigma_y)
        if used == SIFT:
            assert pf.mode == (GLOBAL if spread < 7.0 else SIFT)
        else:
            assert pf.mode == (SIFT if spread > 5.5 else GLOBAL)
        modes.append(used)
    assert GLOBAL in modes  # a confident filter does go global


def test_thresholds_scale_with_motion_sigma():
    map_xy = _route()
    pf = ParticleFilter(map_xy, cKDTree(map_xy), FilterConfig(),
                        MotionModel(sigma_floor=4.0, speed=7.0, nominal_dt=5.0), 2.0,
                        np.random.default_rng(0))
    k = np.hypot(4.0, 35.0) / 4.0
    assert pf.thresholds() == pytest.approx((5.5 * k, 7.0 * k))


def test_zero_similarity_everywhere_keeps_uniform_weights():
    map_xy = _route()
    pf = ParticleFilter(map_xy, cKDTree(map_xy), FilterConfig(replace_fraction=0.0),
                        MotionModel(), 2.0, np.random.default_rng(0))
    pf.step(lambda idx: np.zeros(len(idx)), None)
    np.testing.assert_allclose(pf.w, 1.0 / len(pf.w))


def test_worst_five_percent_replaced_and_weights_renormalised():
    map_xy = _route()
    m = 200
    pf = ParticleFilter(map_xy, cKDTree(map_xy), FilterConfig(n_particles=m),
                        MotionModel(sigma_floor=1.0, pull=0.0), 2.0, np.random.default_rng(4))
    # Only image 0 looks like the frame: every other particle gets weight zero, so the
    # worst 5 % are zero-weight ones and the sum after replacement is 1 + 10/m.
    pf.step(lambda idx: (idx == 0).astype(float), None)
    assert pf.w.sum() == pytest.approx(1.0)
    assert np.sum(np.isclose(pf.w, 1.0 / (m + 10), rtol=1e-12)) == 10


# -- serialisation -----------------------------------------------------------------------


def test_serialised_state_resumes_bit_for_bit():
    map_xy = _route()

    def make(seed):
        return ParticleFilter(map_xy, cKDTree(map_xy), CONFIGS["default"],
                              MotionModel(sigma_floor=2.0, speed=1.0, velocity=True), 2.0,
                              np.random.default_rng(seed))

    a = make(9)
    for k in range(5):
        a.step(_perfect(map_xy, map_xy[k]), 1.0)
    arrays, meta = a.state()
    b = make(123)  # another seed: everything must come from the state
    b.load({k: v.copy() for k, v in arrays.items()}, meta)
    for k in range(5, 12):
        sa, *_ = a.step(_perfect(map_xy, map_xy[k]), 1.0)
        sb, *_ = b.step(_perfect(map_xy, map_xy[k]), 1.0)
        assert np.array_equal(sa.mean, sb.mean)
    assert np.array_equal(a.xy, b.xy) and np.array_equal(a.w, b.w)


# -- configuration -----------------------------------------------------------------------


def test_weiss2008_is_the_paper():
    c = CONFIGS["weiss2008"]
    assert (c.n_particles, c.motion_sigma, c.pull, c.global_power, c.replace_fraction,
            c.d_global, c.d_sift, c.replacement, c.global_features, c.global_measure) == (
        300, 4.0, 0.2, 20.0, 0.05, 5.5, 7.0, "uniform", ("wgoh", "wgii"), "weiss")


@pytest.mark.parametrize("bad", [{"n_particles": 0}, {"pull": 1.5}, {"motion_sigma": float("nan")},
                                 {"nonsense": 1}, {"config": "nope"}, {"sift_verify": "maybe"},
                                 {"global_features": ["colour"]}, {"global_measure": "cosine"}])
def test_bad_parameters_are_refused_clearly(bad):
    with pytest.raises(ValueError):
        config_from_params(bad)
