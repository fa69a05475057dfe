"""Shortlist codes of a large map's place descriptors, against the exact product."""

from __future__ import annotations

import numpy as np
import pytest

from vloc.workers.core.features.shortlist import PlaceCodes


def _unit(rows: np.ndarray) -> np.ndarray:
    return (rows / np.linalg.norm(rows, axis=1, keepdims=True)).astype(np.float32)


def _places(rng, n=6000, d=256, rank=48):
    """VLAD-like descriptors: unit vectors mostly in a low-dimensional subspace (the
    vocabulary's common directions) plus a share of noise of their own."""
    mix = rng.normal(size=(rank, d))
    return _unit(rng.normal(size=(n, rank)) @ mix + 0.6 * rng.normal(size=(n, d)) * np.sqrt(rank / d))


def test_basis_is_orthonormal_and_codes_are_the_projection():
    rng = np.random.default_rng(0)
    M = _places(rng, n=500, d=64)
    pc = PlaceCodes.fit(M, dims=16)
    assert pc.basis.shape == (64, 16) and pc.codes.shape == (500, 16)
    np.testing.assert_allclose(pc.basis.T @ pc.basis, np.eye(16), atol=1e-5)
    np.testing.assert_allclose(pc.codes, M @ pc.basis, atol=1e-5)


def test_the_directions_are_those_of_largest_second_moment():
    # descriptors spread mostly along two known axes: those are the first two directions
    rng = np.random.default_rng(1)
    M = np.zeros((400, 8), np.float32)
    M[:, 3] = rng.normal(scale=5.0, size=400)
    M[:, 6] = rng.normal(scale=2.0, size=400)
    M += rng.normal(scale=0.05, size=M.shape).astype(np.float32)
    pc = PlaceCodes.fit(M, dims=2)
    assert abs(pc.basis[3, 0]) > 0.999 and abs(pc.basis[6, 1]) > 0.999


def test_fit_from_a_sample_is_repeatable():
    rng = np.random.default_rng(2)
    M = _places(rng, n=3000, d=64)
    a, b = PlaceCodes.fit(M, dims=8, sample=1000), PlaceCodes.fit(M, dims=8, sample=1000)
    np.testing.assert_array_equal(a.basis, b.basis)
    np.testing.assert_array_equal(a.codes, b.codes)


def test_full_dimensional_codes_shortlist_exactly_the_best_images():
    rng = np.random.default_rng(3)
    M = _places(rng, n=2000, d=32)
    pc = PlaceCodes.fit(M, dims=32)
    for q in _unit(M[:20] + 0.3 * rng.normal(size=(20, 32))):
        exact = M @ q  # the slow obvious reference: every image, sorted
        want = np.sort(np.argsort(-exact)[:50])
        np.testing.assert_array_equal(pc.shortlist(q, 50), want)


@pytest.mark.parametrize("seed", range(3))
def test_shortlist_holds_the_exact_best_images_of_a_large_map(seed):
    rng = np.random.default_rng(10 + seed)
    M = _places(rng)
    pc = PlaceCodes.fit(M, dims=32, sample=2000, seed=seed)
    rows = rng.choice(len(M), size=40, replace=False)
    # a frame looks like its place, under other light and viewpoint: half of it is new
    queries = _unit(M[rows] + rng.normal(size=(40, M.shape[1])) * 0.06)
    hits = 0
    for q in queries:
        best = np.argsort(-(M @ q))[:10]
        hits += np.isin(best, pc.shortlist(q, 256)).sum()
    assert hits / (10 * len(queries)) >= 0.97


def test_a_shortlist_of_a_small_map_is_every_image():
    M = _places(np.random.default_rng(4), n=30, d=16)
    np.testing.assert_array_equal(PlaceCodes.fit(M, dims=4).shortlist(M[0], 512), np.arange(30))


def test_codes_must_fit_their_basis():
    with pytest.raises(ValueError, match="do not fit"):
        PlaceCodes(np.zeros((16, 4), np.float32), np.zeros((10, 5), np.float32))
