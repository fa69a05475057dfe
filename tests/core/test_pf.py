"""The particle filter against known distributions and known answers."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from vloc.workers.core.pf.clusters import cluster_labels, heaviest_cluster
from vloc.workers.core.pf.config import (
    CONFIGS,
    DEFAULT_OVERRIDES,
    PARAMS,
    WEISS2008,
    FilterConfig,
    config_from_params,
)
from vloc.workers.core.pf.filter import ParticleFilter, cloud_sample, cloud_stats
from vloc.workers.core.pf.measurement import (
    ImageSimilarity,
    Likelihood,
    Position,
    distance_factor,
    log_likelihoods,
    normalise_log,
)
from vloc.workers.core.pf.motion import MotionModel
from vloc.workers.core.pf.resampling import multinomial, systematic
from vloc.workers.core.pf.switching import GLOBAL, SIFT

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


def test_image_similarity_scores_each_distinct_nearest_image_once():
    map_xy = np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 0.0]])
    asked = []

    def sim(idx):
        asked.append(idx.copy())
        return np.array([0.2, 0.5, 0.9])[idx]

    xy = np.array([[1.0, 0.0], [9.0, 0.0], [11.0, 0.0], [0.0, 2.0]])
    lk = ImageSimilarity(SIFT, sim, power=2.0, scale=5.0).likelihood(xy, cKDTree(map_xy))
    assert len(asked) == 1 and asked[0].tolist() == [0, 1]  # image 2 is nobody's nearest
    d = np.array([1.0, 1.0, 1.0, 2.0])
    s = np.array([0.2, 0.5, 0.5, 0.2])
    np.testing.assert_allclose(lk.log, 2.0 * np.log(s) - 0.5 * (d / 5.0) ** 2, rtol=1e-12)
    assert lk.kind == SIFT and lk.power == 2.0
    assert lk.scored.tolist() == [0, 1] and lk.similarities.tolist() == [0.2, 0.5]
    # each particle's nearest image, as looked up: later steps of the frame reuse it
    assert lk.nearest.tolist() == [0, 1, 1, 0]


def test_image_similarity_every_image_and_candidates():
    map_xy = np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 0.0], [30.0, 0.0]])
    xy = np.array([[1.0, 0.0]])
    tree = cKDTree(map_xy)

    def sim(idx):
        return idx / 10.0 + 0.1

    every = ImageSimilarity(GLOBAL, sim, 1.0, 5.0, every_image=True).likelihood(xy, tree)
    assert every.scored.tolist() == [0, 1, 2, 3]
    shortlisted = ImageSimilarity(SIFT, sim, 1.0, 5.0, candidates=np.array([3])).likelihood(
        xy, tree)
    assert shortlisted.scored.tolist() == [0, 3]
    np.testing.assert_allclose(every.log, shortlisted.log)


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


def _cloud_sample_by_loop(xy, w, k):
    """Walk the particles once, taking each target offset as its particle is passed."""
    total, out, acc, i = float(np.sum(w)), [], 0.0, 0
    for j in range(k):
        target = (j + 0.5) / k * total
        while acc + w[i] <= target and i < len(w) - 1:
            acc += w[i]
            i += 1
        out.append(xy[i])
    return np.array(out)


def test_cloud_sample_by_hand():
    xy = np.array([[0.0, 0.0], [1.0, 1.0], [2.0, 2.0], [3.0, 3.0]])
    w = np.array([0.5, 0.0, 0.25, 0.25])
    # offsets 1/6, 1/2, 5/6 of the cumulative weights 0.5, 0.5, 0.75, 1; a target on a
    # boundary goes to the next particle of non-zero weight
    np.testing.assert_array_equal(cloud_sample(xy, w, k=3), xy[[0, 2, 3]])
    np.testing.assert_array_equal(cloud_sample(xy, w, k=3), _cloud_sample_by_loop(xy, w, 3))
    # a cloud no larger than the sample comes back whole, zero weights included
    np.testing.assert_array_equal(cloud_sample(xy, w, k=4), xy)


def test_cloud_sample_matches_a_loop_and_follows_the_weights():
    rng = np.random.default_rng(4)
    xy = rng.normal(size=(500, 2))
    w = rng.gamma(0.3, size=500)
    w /= w.sum()
    got = cloud_sample(xy, w, k=64)
    np.testing.assert_array_equal(got, _cloud_sample_by_loop(xy, w, 64))
    counts = np.array([np.sum(np.all(got == p, axis=1)) for p in xy])
    # systematic selection: every particle is drawn floor or ceil of 64 w times, +-1
    assert np.all(np.abs(counts - 64 * w) < 2)
    assert counts.sum() == 64
    state = rng.bit_generator.state
    cloud_sample(xy, w)
    assert rng.bit_generator.state == state


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


def _measure(sim, kind=SIFT, power=1.0, scale=2.0):
    return ImageSimilarity(kind, sim, power, scale)


@pytest.mark.parametrize("config", ["weiss2008", "default"])
def test_filter_with_perfect_similarity_converges_to_truth(config):
    map_xy = _route()
    cfg = CONFIGS[config]
    pf = ParticleFilter(map_xy, cKDTree(map_xy), cfg,
                        MotionModel(sigma_floor=2.0, speed=1.0, velocity=cfg.motion.velocity),
                        2.0, np.random.default_rng(5))
    errors = []
    for k in range(40):
        truth = map_xy[(10 + k) % len(map_xy)]
        result = pf.step([_measure(_perfect(map_xy, truth))], 1.0)
        errors.append(np.linalg.norm(result.stats.mean - truth))
    assert np.mean(errors[-20:]) < 3.0


def test_step_result_names_the_measurements_used():
    map_xy = _route()
    pf = ParticleFilter(map_xy, cKDTree(map_xy), WEISS2008, MotionModel(), 2.0,
                        np.random.default_rng(0))
    sim = _perfect(map_xy, map_xy[0])
    assert pf.step([_measure(sim, GLOBAL, 20.0)], None).kinds == (GLOBAL,)
    assert pf.step([_measure(sim), _measure(sim, GLOBAL)], None).kinds == (SIFT, GLOBAL)


class _Flat:
    """A measurement that likes one half-plane: log-likelihood 0 for x > 0, -inf elsewhere."""

    kind = "east"

    def likelihood(self, xy, tree):
        return Likelihood(self.kind, np.where(xy[:, 0] > 0, 0.0, -np.inf))


def test_measurements_in_one_step_multiply():
    map_xy = _route()
    cfg = WEISS2008.with_params(replace_fraction=0.0)
    pf = ParticleFilter(map_xy, cKDTree(map_xy), cfg, MotionModel(pull=0.0), 2.0,
                        np.random.default_rng(1))
    sim = _perfect(map_xy, map_xy[0], 20.0)
    before = pf.xy.copy()
    result = pf.step([_measure(sim), _Flat()], None)
    assert result.kinds == (SIFT, "east")
    assert np.all(pf.w[pf.xy[:, 0] <= 0] == 0.0)  # the second measurement vetoes the west
    # and where both allow, the weights follow the image similarity alone
    east = pf.xy[:, 0] > 0
    image = result.likelihoods[0].log[east]
    np.testing.assert_allclose(pf.w[east], np.exp(image - image.max()) /
                               np.exp(image - image.max()).sum(), rtol=1e-9)
    assert not np.array_equal(before, pf.xy)


@pytest.mark.parametrize("alone", [False, True])
def test_a_position_alone_replaces_the_image_similarity_in_the_weights(alone):
    map_xy = _route()
    cfg = WEISS2008.with_params(replace_fraction=0.0)
    pf = ParticleFilter(map_xy, cKDTree(map_xy), cfg, MotionModel(pull=0.0), 2.0,
                        np.random.default_rng(3))
    # the images say the platform is at image 0; the position says image 30
    fix = Position("registered", map_xy[30].copy(), 4.0, 0.05, alone=alone)
    result = pf.step([_measure(_perfect(map_xy, map_xy[0], 20.0))], None,
                     refine=lambda likelihoods: fix)
    assert result.kinds == (SIFT, "registered")
    image, position = (lk.log for lk in result.likelihoods)
    expected = position if alone else image + position
    np.testing.assert_allclose(pf.w, np.exp(expected - expected.max())
                               / np.exp(expected - expected.max()).sum(), rtol=1e-9)
    # by hand: the position's Gaussian with its outlier floor
    d2 = np.sum((pf.xy - map_xy[30]) ** 2, axis=1)
    np.testing.assert_allclose(position, np.log(0.95 * np.exp(-0.5 * d2 / 16.0) + 0.05))
    # alone, the heaviest particle lies by the position; multiplied, the images pull it away
    best = pf.xy[np.argmax(pf.w)]
    assert (np.linalg.norm(best - map_xy[30]) < 8.0) == alone


@pytest.mark.parametrize("point_estimate", ["mean", "cluster"])
def test_the_reported_position_is_the_heaviest_cluster_s_where_configured(point_estimate):
    map_xy = _route()
    cfg = WEISS2008.with_params(replace_fraction=0.0, point_estimate=point_estimate)
    pf = ParticleFilter(map_xy, cKDTree(map_xy), cfg, MotionModel(pull=0.0, sigma_floor=1.0),
                        2.0, np.random.default_rng(3), spacing=8.0)
    assert pf.cluster_cell == pytest.approx(8.0 / (2 * np.sqrt(2)))
    # never narrower than the motion's floor
    dense = ParticleFilter(map_xy, cKDTree(map_xy), cfg, MotionModel(sigma_floor=4.0), 2.0,
                           np.random.default_rng(3), spacing=0.5)
    assert dense.cluster_cell == 4.0
    # a sharp fix at image 30 over a cloud spread along the whole route
    fix = Position("registered", map_xy[30].copy(), 2.0, 0.05, alone=True)
    result = pf.step([_measure(_perfect(map_xy, map_xy[0], 20.0))], None,
                     refine=lambda likelihoods: fix)
    # nothing replaced: the filter's arrays are the weighted cloud the step estimated from
    np.testing.assert_array_equal(result.stats.mean, cloud_stats(pf.xy, pf.w).mean)
    if point_estimate == "mean":
        assert result.estimate is result.stats and result.spread == result.stats.spread
        return
    members, share = heaviest_cluster(pf.xy, pf.w, pf.cluster_cell)
    assert share > 0.5
    own = cloud_stats(pf.xy[members], pf.w[members] / pf.w[members].sum())
    np.testing.assert_allclose(result.estimate.mean, own.mean, rtol=1e-12)
    np.testing.assert_allclose(result.estimate.cov,
                               cloud_stats(pf.xy, pf.w, about=own.mean).cov, rtol=1e-12)
    # the cluster's position is by the fix; the whole cloud's is pulled away by the strays
    assert np.linalg.norm(own.mean - map_xy[30]) < 2.0
    assert np.linalg.norm(result.stats.mean - map_xy[30]) > \
        np.linalg.norm(own.mean - map_xy[30])
    # the covariance reported is about the cluster's position: never tighter than the
    # cloud's own; the switching rule judges the cluster's own spread, tighter than both
    assert result.estimate.spread >= result.stats.spread
    assert result.spread == own.spread < result.stats.spread


def test_a_cloud_without_a_majority_cluster_reports_its_mean():
    map_xy = _route()
    cfg = WEISS2008.with_params(replace_fraction=0.0, point_estimate="cluster")
    pf = ParticleFilter(map_xy, cKDTree(map_xy), cfg, MotionModel(pull=0.0, sigma_floor=0.5),
                        2.0, np.random.default_rng(4), spacing=8.0)
    # three hypotheses a third of the route apart, the frame alike everywhere: none holds
    # most of the weight
    rng = np.random.default_rng(5)
    pf.xy = np.concatenate([map_xy[i] + rng.normal(0, 0.5, size=(100, 2)) for i in (0, 40, 80)])
    pf.w = np.full(300, 1.0 / 300)
    result = pf.step([_measure(lambda idx: np.ones(len(idx)))], None)
    assert len(np.unique(cluster_labels(pf.xy, pf.cluster_cell))) == 3
    _, share = heaviest_cluster(pf.xy, pf.w, pf.cluster_cell)
    assert share < 0.5
    assert result.estimate is result.stats and result.spread == result.stats.spread


def test_zero_similarity_everywhere_keeps_uniform_weights():
    map_xy = _route()
    pf = ParticleFilter(map_xy, cKDTree(map_xy), WEISS2008.with_params(replace_fraction=0.0),
                        MotionModel(), 2.0, np.random.default_rng(0))
    pf.step([_measure(lambda idx: np.zeros(len(idx)))], None)
    np.testing.assert_allclose(pf.w, 1.0 / len(pf.w))


def test_worst_five_percent_replaced_and_weights_renormalised():
    map_xy = _route()
    m = 200
    pf = ParticleFilter(map_xy, cKDTree(map_xy), WEISS2008.with_params(n_particles=m),
                        MotionModel(sigma_floor=1.0, pull=0.0), 2.0, np.random.default_rng(4))
    # Only image 0 looks like the frame: every other particle gets weight zero, so the
    # worst 5 % are zero-weight ones and the sum after replacement is 1 + 10/m.
    pf.step([_measure(lambda idx: (idx == 0).astype(float))], None)
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
        a.step([_measure(_perfect(map_xy, map_xy[k]))], 1.0)
    arrays, meta = a.state()
    b = make(123)  # another seed: everything must come from the state
    b.load({k: v.copy() for k, v in arrays.items()}, meta)
    for k in range(5, 12):
        ra = a.step([_measure(_perfect(map_xy, map_xy[k]))], 1.0)
        rb = b.step([_measure(_perfect(map_xy, map_xy[k]))], 1.0)
        assert np.array_equal(ra.stats.mean, rb.stats.mean)
    assert np.array_equal(a.xy, b.xy) and np.array_equal(a.w, b.w)


# -- configuration -----------------------------------------------------------------------


def test_weiss2008_is_the_paper():
    c = CONFIGS["weiss2008"]
    assert c is WEISS2008
    assert (c.n_particles, c.resampler, c.motion.sigma, c.motion.pull, c.motion.velocity,
            c.measurement.global_power, c.measurement.sift_power,
            c.measurement.global_features, c.measurement.global_measure,
            c.sift.verify, c.sift.reduce, c.switching.d_global, c.switching.d_sift,
            c.switching.global_check, c.switching.global_trust, c.reset.fraction,
            c.reset.replacement) == (
        300, "multinomial", 4.0, 0.2, False, 20.0, 1.0, ("wgoh", "wgii"), "weiss", "none",
        "both", 5.5, 7.0, 0, 0, 0.05, "uniform")


def test_default_is_weiss2008_with_its_overrides_alone():
    base, default = CONFIGS["weiss2008"].to_params(), CONFIGS["default"].to_params()
    changed = {k: v for k, v in default.items() if base[k] != v}
    assert changed == DEFAULT_OVERRIDES


def test_flat_parameters_reach_their_part_and_come_back():
    c = config_from_params({"config": "weiss2008", "n_particles": 50, "sift_ratio": 0.75,
                            "global_features": "wgoh", "global_trust_level": 0.5,
                            "replace_fraction": 0.1, "motion_sigma": 3.0})
    assert (c.n_particles, c.sift.ratio, c.measurement.global_features,
            c.switching.global_trust_level, c.reset.fraction, c.motion.sigma) == (
        50, 0.75, ("wgoh",), 0.5, 0.1, 3.0)
    flat = c.to_params()
    assert list(flat) == list(PARAMS) and flat["global_features"] == ["wgoh"]
    assert config_from_params({"config": "weiss2008", **flat}) == c


def test_every_field_of_every_part_has_one_flat_name():
    from dataclasses import fields

    paths = {(p.part, p.field) for p in PARAMS.values()}
    assert len(paths) == len(PARAMS)
    for f in fields(FilterConfig):
        part = getattr(WEISS2008, f.name)
        if hasattr(part, "__dataclass_fields__"):
            assert {(f.name, g.name) for g in fields(part)} <= paths
        else:
            assert (None, f.name) in paths


@pytest.mark.parametrize("bad", [{"n_particles": 0}, {"pull": 1.5}, {"motion_sigma": float("nan")},
                                 {"nonsense": 1}, {"config": "nope"}, {"sift_verify": "maybe"},
                                 {"global_features": ["colour"]}, {"global_measure": "cosine"}])
def test_bad_parameters_are_refused_clearly(bad):
    with pytest.raises(ValueError):
        config_from_params(bad)
