"""Similarity measures: hand-computed values, loop references, bounds and errors."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from vloc.workers.core.measures import (
    D_MAX,
    MEASURES,
    distances,
    normalise,
    similarities,
    weiss_similarity,
)

Q = np.array([0.5, 0.25, 0.25, 0.0])
M1 = np.array([0.25, 0.25, 0.25, 0.25])
COS = math.sqrt(2 / 3)  # (0.125 + 0.0625 + 0.0625) / (sqrt(0.375) * 0.5)

HAND = {  # measure: (distance, similarity) of Q and M1, both summing to 1
    "l1": (0.5, 0.75),
    "l2": (math.sqrt(2 - 2 * COS), 1 - math.sqrt(2 - 2 * COS) / math.sqrt(2)),
    "linf": (0.25, 0.75),
    "intersection": (0.25, 0.75),
    "bradley": (1 - COS, COS),
    "weiss": (0.25, 0.75),
}


@pytest.mark.parametrize("measure", MEASURES)
def test_hand_computed_values(measure):
    d, s = HAND[measure]
    M = np.stack([M1, Q])
    np.testing.assert_allclose(distances(measure, Q, M), [d, 0.0], atol=1e-12)
    np.testing.assert_allclose(similarities(measure, Q, M), [s, 1.0], atol=1e-12)


@pytest.mark.parametrize("measure", ["l1", "l2", "linf", "intersection", "bradley"])
def test_normalising_measures_ignore_the_scale_of_the_inputs(measure):
    np.testing.assert_allclose(distances(measure, 4 * Q, 3 * M1[None]),
                               [HAND[measure][0]], atol=1e-12)


def test_weiss_is_equation_1_on_raw_vectors_and_asymmetric():
    q = np.array([2.0, 1.0, 1.0, 0.0])
    d = np.array([1.0, 1.0, 1.0, 3.0])
    # sum min = 1 + 1 + 1 + 0 = 3; divided by the query's mass
    assert similarities("weiss", q, d[None])[0] == pytest.approx(3 / 4)
    assert similarities("weiss", d, q[None])[0] == pytest.approx(3 / 6)
    # the intersection normalises both first: sum min(q/4, d/6)
    expected = sum(min(a / 4, b / 6) for a, b in zip(q, d, strict=True))
    assert similarities("intersection", q, d[None])[0] == pytest.approx(expected)


def test_normalise_by_measure():
    v = np.array([[3.0, 4.0, 0.0], [0.0, 0.0, 0.0]])
    np.testing.assert_allclose(normalise(v, "l1"), [[3 / 7, 4 / 7, 0], [0, 0, 0]])
    np.testing.assert_allclose(normalise(v, "bradley"), [[0.6, 0.8, 0], [0, 0, 0]])
    np.testing.assert_allclose(normalise(v, "l2"), [[0.6, 0.8, 0], [0, 0, 0]])
    np.testing.assert_allclose(normalise(v[0], "intersection"), [3 / 7, 4 / 7, 0])
    np.testing.assert_array_equal(normalise(v, "weiss"), v)
    assert normalise(v[0], "linf").sum() == pytest.approx(1.0)


def _loop_distance(measure: str, q: np.ndarray, m: np.ndarray) -> float:
    """Per-element Python loops, straight from the formulas."""
    if measure in ("l1", "linf", "intersection"):
        q, m = q / sum(q), m / sum(m)
    elif measure in ("l2", "bradley"):
        q, m = q / math.sqrt(sum(x * x for x in q)), m / math.sqrt(sum(x * x for x in m))
    pairs = list(zip(q, m, strict=True))
    if measure == "l1":
        return sum(abs(a - b) for a, b in pairs)
    if measure == "l2":
        return math.sqrt(sum((a - b) ** 2 for a, b in pairs))
    if measure == "linf":
        return max(abs(a - b) for a, b in pairs)
    if measure == "intersection":
        return 1 - sum(min(a, b) for a, b in pairs)
    if measure == "bradley":
        return 1 - sum(a * b for a, b in pairs)
    return 1 - sum(min(a, b) for a, b in pairs) / sum(q)  # weiss


@pytest.mark.parametrize("measure", MEASURES)
def test_vectorised_equals_per_row_loop(measure):
    rng = np.random.default_rng(2)
    M = rng.random((40, 16)) * (rng.random((40, 16)) < 0.6)
    M[3] = M[0]
    q = M[0] * 0.7 + 0.3 * rng.random(16)
    fast = distances(measure, q, M)
    slow = [_loop_distance(measure, q, row) for row in M]
    np.testing.assert_allclose(fast, slow, atol=1e-12)
    one_by_one = [distances(measure, q, row[None])[0] for row in M]
    np.testing.assert_allclose(fast, one_by_one, atol=1e-15)


@pytest.mark.parametrize("measure", MEASURES)
def test_similarity_is_one_minus_distance_over_its_maximum(measure):
    rng = np.random.default_rng(4)
    M = rng.random((30, 8))
    q = rng.random(8)
    d = distances(measure, q, M)
    np.testing.assert_allclose(similarities(measure, q, M), 1 - d / D_MAX[measure])


@pytest.mark.parametrize("measure", MEASURES)
def test_maximum_distance_is_reached_by_disjoint_histograms(measure):
    q = np.array([1.0, 0.0, 0.0])
    M = np.array([[0.0, 1.0, 0.0], [0.0, 0.3, 0.7]])
    # l2: |q - m|^2 = |q|^2 + |m|^2 = 2 after L2 scaling; linf: q's bin differs by 1
    np.testing.assert_allclose(distances(measure, q, M), [D_MAX[measure]] * 2, atol=1e-12)
    np.testing.assert_allclose(similarities(measure, q, M), [0.0, 0.0], atol=1e-12)


def test_l1_similarity_is_the_intersection_and_l2_ranks_as_bradley():
    rng = np.random.default_rng(6)
    M = rng.random((50, 12))
    q = rng.random(12)
    np.testing.assert_allclose(similarities("l1", q, M), similarities("intersection", q, M))
    assert (np.argsort(distances("l2", q, M)) == np.argsort(distances("bradley", q, M))).all()


@pytest.mark.parametrize("measure", MEASURES)
def test_prenormalised_inputs_skip_normalisation_with_the_same_result(measure):
    rng = np.random.default_rng(8)
    M = rng.random((20, 10))
    q = rng.random(10)
    np.testing.assert_allclose(
        similarities(measure, normalise(q, measure), normalise(M, measure), normalised=True),
        similarities(measure, q, M), atol=1e-15)


@pytest.mark.parametrize("measure", MEASURES)
def test_empty_histograms_match_nothing(measure):
    q = np.array([0.2, 0.8, 0.0])
    M = np.array([[0.0, 0.0, 0.0], [0.2, 0.8, 0.0]])
    np.testing.assert_allclose(similarities(measure, q, M), [0.0, 1.0], atol=1e-12)
    assert distances(measure, q, M)[0] == D_MAX[measure]
    np.testing.assert_array_equal(similarities(measure, np.zeros(3), M), [0.0, 0.0])


def test_weiss_similarity_is_the_product_of_the_two_intersections():
    rng = np.random.default_rng(9)
    Mo, Mi = rng.random((25, 128)), rng.random((25, 128))
    qo, qi = rng.random(128), rng.random(128)
    s = weiss_similarity(qo, Mo, qi, Mi)
    np.testing.assert_allclose(s, similarities("weiss", qo, Mo) * similarities("weiss", qi, Mi))
    assert s.shape == (25,) and s.dtype == np.float64
    assert weiss_similarity(qo, qo[None], qi, qi[None])[0] == pytest.approx(1.0)
    with pytest.raises(ValueError, match="rows"):
        weiss_similarity(qo, Mo, qi, Mi[:3])


def test_errors_are_clear():
    with pytest.raises(ValueError, match="bradley"):  # lists the valid measures
        distances("cosine", Q, M1[None])
    with pytest.raises(ValueError, match="cosine"):
        normalise(Q, "cosine")
    with pytest.raises(ValueError, match=r"\(D,\)"):
        similarities("l1", Q, np.ones((3, 5)))
    with pytest.raises(ValueError):
        similarities("l1", Q[None], M1[None])
    with pytest.raises(ValueError):
        similarities("l1", Q, M1)
    bad_q = Q.copy()
    bad_q[1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        similarities("l2", bad_q, M1[None])
    bad_M = np.stack([M1, M1])
    bad_M[1, 2] = np.nan
    for measure in MEASURES:
        with pytest.raises(ValueError, match="NaN"):
            similarities(measure, Q, bad_M, normalised=True)
    bad_M[1, 2] = np.inf
    with pytest.raises(ValueError, match="infinite"):
        similarities("intersection", Q, bad_M, normalised=True)
    with pytest.raises(ValueError, match="non-negative"):
        similarities("weiss", -Q, M1[None])


def test_an_empty_map_gives_an_empty_answer():
    assert similarities("weiss", Q, np.zeros((0, 4))).shape == (0,)


# bins are 0 or well above underflow: a squared norm of 1e-300 would vanish to 0
bin_values = st.one_of(st.just(0.0), st.floats(1e-6, 1e3))
histograms = arrays(np.float64, st.integers(1, 12), elements=bin_values)


@settings(max_examples=150, deadline=None)
@given(st.data())
def test_similarities_lie_in_0_1_and_a_vector_matches_itself(data):
    q = data.draw(histograms)
    rows = data.draw(st.lists(arrays(np.float64, q.shape, elements=bin_values),
                              min_size=1, max_size=5))
    M = np.stack([q, *rows])
    for measure in MEASURES:
        s = similarities(measure, q, M)
        assert s.shape == (len(M),)
        assert ((s >= 0) & (s <= 1)).all()
        if q.any():
            assert s[0] == pytest.approx(1.0, abs=1e-9)
        if measure != "weiss":  # all others are symmetric
            back = [similarities(measure, row, q[None])[0] for row in M]
            np.testing.assert_allclose(s, back, atol=1e-9)


@pytest.mark.parametrize("measure", MEASURES)
def test_inputs_are_left_untouched(measure):
    rng = np.random.default_rng(10)
    M = rng.random((6, 5))
    q = rng.random(5)
    M_before, q_before = M.copy(), q.copy()
    for flag in (False, True):
        similarities(measure, q, M, normalised=flag)
        normalise(M, measure)
    np.testing.assert_array_equal(M, M_before)
    np.testing.assert_array_equal(q, q_before)


def test_descriptor_similarities_are_clipped_cosines():
    from vloc.workers.core.measures import descriptor_similarities

    q = np.array([0.6, 0.8, 0.0], np.float32)
    M = np.array([[0.6, 0.8, 0.0], [0.0, 0.0, 1.0], [-0.6, -0.8, 0.0], [0.8, 0.6, 0.0],
                  [0.0, 0.0, 0.0]], np.float32)
    np.testing.assert_allclose(descriptor_similarities(q, M), [1.0, 0.0, 0.0, 0.96, 0.0],
                               atol=1e-6)
    np.testing.assert_allclose(descriptor_similarities(q, M, np.array([3, 0])), [0.96, 1.0],
                               atol=1e-6)


def test_descriptor_similarities_equal_a_loop_for_any_subset():
    from vloc.workers.core.measures import descriptor_similarities

    rng = np.random.default_rng(12)
    M = rng.standard_normal((40, 9)).astype(np.float32)
    M /= np.linalg.norm(M, axis=1, keepdims=True)
    q = M[7] + 0.5 * rng.standard_normal(9).astype(np.float32)
    q /= np.linalg.norm(q)
    slow = [max(sum(float(a) * float(b) for a, b in zip(q, row, strict=True)), 0.0) for row in M]
    for idx in (None, np.array([5]), np.arange(0, 40, 2)):
        want = slow if idx is None else [slow[i] for i in idx]
        np.testing.assert_allclose(descriptor_similarities(q, M, idx), want, atol=1e-6)
    with pytest.raises(ValueError, match="NaN"):
        descriptor_similarities(np.full(9, np.nan, np.float32), M)
    with pytest.raises(ValueError, match=r"\(D,\)"):
        descriptor_similarities(q[:4], M)
