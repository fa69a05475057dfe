"""The cloud's clusters and the position a multimodal cloud reports
(:mod:`workers.core.pf.clusters`), against known answers and a slow pairwise reference."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from vloc.workers.core.pf.clusters import cluster_labels, heaviest_cluster
from vloc.workers.core.pf.filter import cloud_stats


def _reference_partition(xy: np.ndarray, cell_m: float) -> set[frozenset[int]]:
    """Every pair of particles whose cells touch (side or corner), joined by union-find."""
    cells = [tuple(int(c) for c in np.floor(p / cell_m)) for p in xy]
    parent = list(range(len(xy)))

    def root(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i, j in itertools.combinations(range(len(xy)), 2):
        if max(abs(a - b) for a, b in zip(cells[i], cells[j], strict=True)) <= 1:
            parent[root(i)] = root(j)
    groups: dict[int, set[int]] = {}
    for i in range(len(xy)):
        groups.setdefault(root(i), set()).add(i)
    return {frozenset(g) for g in groups.values()}


def _partition(labels: np.ndarray) -> set[frozenset[int]]:
    return {frozenset(np.flatnonzero(labels == k).tolist()) for k in np.unique(labels)}


@pytest.mark.parametrize("seed", range(6))
def test_clusters_match_the_pairwise_reference(seed):
    rng = np.random.default_rng(seed)
    # a few dense hypotheses and a spread of stray particles, as a lost cloud looks
    centres = rng.uniform(-300, 300, size=(4, 2))
    xy = np.concatenate([c + rng.normal(0, rng.uniform(1, 15), size=(40, 2)) for c in centres]
                        + [rng.uniform(-400, 400, size=(40, 2))])
    for cell in (2.0, 7.5, 30.0):
        labels = cluster_labels(xy, cell)
        assert _partition(labels) == _reference_partition(xy, cell)
        assert labels.min() == 0 and set(labels.tolist()) == set(range(labels.max() + 1))


def test_a_long_chain_is_one_cluster_and_a_gap_cuts_it():
    # a line of particles a little under a cell apart: many rounds of joining
    xy = np.column_stack([np.arange(400) * 0.9, np.zeros(400)])
    assert np.all(cluster_labels(xy, 1.0) == 0)
    gapped = xy.copy()
    gapped[200:, 0] += 10.0
    labels = cluster_labels(gapped, 1.0)
    assert np.all(labels[:200] == 0) and np.all(labels[200:] == 1)
    # diagonal chains join through corners; the north-west corner too
    diag = np.column_stack([np.arange(50) * 1.0 + 0.5, -np.arange(50) * 1.0 + 0.5])
    assert np.all(cluster_labels(diag, 1.0) == 0)


def test_particles_closer_than_a_cell_always_share_a_cluster():
    rng = np.random.default_rng(7)
    xy = rng.uniform(0, 200, size=(300, 2))
    labels = cluster_labels(xy, 5.0)
    d = np.hypot(*(xy[:, None, :] - xy[None, :, :]).transpose(2, 0, 1))
    i, j = np.nonzero(d < 5.0)
    assert np.all(labels[i] == labels[j])


def test_two_hypotheses_give_the_heavier_one():
    rng = np.random.default_rng(1)
    near = np.array([10.0, -4.0]) + rng.normal(0, 2.0, size=(60, 2))
    far = np.array([400.0, 250.0]) + rng.normal(0, 30.0, size=(240, 2))
    xy = np.concatenate([near, far])
    # most of the weight on the 60 particles around one fix, a little on each stray one
    w = np.concatenate([np.full(60, 0.86 / 60), np.full(240, 0.14 / 240)])
    members, share = heaviest_cluster(xy, w, 10.0)
    assert members[:60].all() and not members[60:].any()
    assert share == pytest.approx(0.86)


def test_one_cluster_holds_every_particle():
    rng = np.random.default_rng(2)
    xy = rng.normal(0, 3.0, size=(100, 2))
    w = rng.random(100)
    w /= w.sum()
    assert np.all(cluster_labels(xy, 50.0) == 0)
    members, share = heaviest_cluster(xy, w, 50.0)
    assert members.all() and share == pytest.approx(1.0)


def test_equal_weights_go_to_the_first_cluster_in_cell_order():
    xy = np.array([[105.0, 5.0], [5.0, 5.0]])
    members, share = heaviest_cluster(xy, np.array([0.5, 0.5]), 10.0)
    assert members.tolist() == [False, True] and share == 0.5
    np.testing.assert_array_equal(cluster_labels(xy, 10.0), [1, 0])


def test_a_single_particle_and_a_bad_cell():
    assert cluster_labels(np.array([[3.0, 4.0]]), 1.0).tolist() == [0]
    members, share = heaviest_cluster(np.array([[3.0, 4.0]]), np.ones(1), 1.0)
    assert members.tolist() == [True] and share == 1.0
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="cell_m"):
            cluster_labels(np.zeros((3, 2)), bad)


def test_the_covariance_about_another_position_adds_the_offset():
    rng = np.random.default_rng(3)
    xy = rng.normal([5.0, -2.0], [3.0, 1.0], size=(500, 2))
    w = rng.random(500)
    w /= w.sum()
    about = np.array([20.0, 4.0])
    mean = cloud_stats(xy, w)
    moved = cloud_stats(xy, w, about=about)
    d = mean.mean - about
    # the second moment about a point is the covariance plus the offset's outer product
    np.testing.assert_allclose(moved.cov, mean.cov + np.outer(d, d), rtol=1e-10)
    np.testing.assert_array_equal(moved.mean, about)
    assert moved.sigma_x == pytest.approx(np.sqrt(moved.cov[0, 0]))
