"""Vocabulary trees: quantisation against a slow descent, training, idf, determinism."""

from __future__ import annotations

import math

import numpy as np
import pytest

from vloc.workers.core.features.distortion import distortion
from vloc.workers.core.features.vocabulary import (
    Projected,
    Vocabulary,
    _sample,
    cluster_sums,
    distinct_rows,
    inverse_document_frequency,
    principal_axes,
    quantise,
    train_vocabulary,
)


def _slow_quantise(vocab: Vocabulary, x: np.ndarray) -> list[int]:
    """Descend the tree one vector and one child at a time, in plain Python."""
    out = []
    for v in x.tolist():
        node = 0
        for level in range(1, vocab.depth + 1):
            first = 0 if level == 1 else node * vocab.branching
            centres = vocab.level(level).tolist()
            best, best_d = None, math.inf
            for child in range(first, first + vocab.branching):
                d = sum((a - b) ** 2 for a, b in zip(v, centres[child], strict=True))
                if d < best_d:
                    best, best_d = child, d
            node = best
        out.append(node)
    return out


def _blobs(rng, centres, n, spread):
    return np.concatenate([c + spread * rng.standard_normal((n, len(c))) for c in centres]
                          ).astype(np.float32)


def test_quantise_equals_the_slow_descent():
    rng = np.random.default_rng(0)
    per_image = [rng.random((60, 6)).astype(np.float32) for _ in range(5)]
    vocab = train_vocabulary(per_image, branching=3, depth=3, binary=False,
                             rng=np.random.default_rng(1))
    assert vocab.n_words == 27 and vocab.centroids.shape == (3 + 9 + 27, 6)
    x = rng.random((40, 6)).astype(np.float32)
    assert quantise(vocab, x).tolist() == _slow_quantise(vocab, x)


def test_binary_quantise_is_the_hamming_descent():
    rng = np.random.default_rng(2)
    per_image = [(rng.random((50, 32)) < 0.5).astype(np.float32) for _ in range(4)]
    vocab = train_vocabulary(per_image, branching=4, depth=2, binary=True,
                             rng=np.random.default_rng(3))
    assert set(np.unique(vocab.centroids)) <= {0.0, 1.0}
    x = (rng.random((30, 32)) < 0.5).astype(np.float32)
    assert quantise(vocab, x).tolist() == _slow_quantise(vocab, x)


def test_flat_kmeans_finds_separated_clusters():
    rng = np.random.default_rng(4)
    truth = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]])
    x = _blobs(rng, truth, 50, 0.3)
    vocab = train_vocabulary([x[:75], x[75:]], branching=3, depth=1, binary=False,
                             rng=np.random.default_rng(5))
    order = np.lexsort(vocab.words.T)
    expected = np.stack([x[i * 50:(i + 1) * 50].mean(axis=0) for i in range(3)])
    np.testing.assert_allclose(vocab.words[order], expected[np.lexsort(expected.T)], atol=1e-4)


def test_k_majority_centres_are_the_bitwise_majority_of_their_members():
    rng = np.random.default_rng(6)
    protos = (rng.random((2, 64)) < 0.5).astype(np.float32)
    flips = rng.random((2, 40, 64)) < 0.1
    x = np.abs(protos[:, None, :] - flips).reshape(-1, 64).astype(np.float32)
    vocab = train_vocabulary([x], branching=2, depth=1, binary=True,
                             rng=np.random.default_rng(7))
    words = quantise(vocab, x)
    for w in range(2):
        members = x[words == w]
        majority = [1.0 if sum(col) > len(members) / 2 else 0.0 for col in members.T.tolist()]
        np.testing.assert_array_equal(vocab.words[w], majority)
    # with 10 % noise per bit the majority recovers the prototypes exactly
    assert {tuple(r) for r in vocab.words.tolist()} == {tuple(r) for r in protos.tolist()}


def test_training_is_deterministic_under_a_seed():
    rng = np.random.default_rng(8)
    per_image = [rng.random((80, 8)).astype(np.float32) for _ in range(6)]

    def train(seed):
        return train_vocabulary(per_image, branching=4, depth=2, binary=False,
                                rng=np.random.default_rng(seed), max_training=300)

    a, b, c = train(11), train(11), train(12)
    np.testing.assert_array_equal(a.centroids, b.centroids)
    np.testing.assert_array_equal(a.idf, b.idf)
    assert not np.array_equal(a.centroids, c.centroids)


def test_fewer_vectors_than_branching_keeps_the_tree_complete():
    x = np.array([[0.0, 0.0], [5.0, 5.0]], np.float32)
    vocab = train_vocabulary([x], branching=4, depth=2, binary=False,
                             rng=np.random.default_rng(0))
    assert vocab.centroids.shape == (4 + 16, 2)
    words = quantise(vocab, x)
    assert len(set(words.tolist())) == 2
    empty = train_vocabulary([np.zeros((0, 2), np.float32)], branching=3, depth=1,
                             binary=False, rng=np.random.default_rng(0))
    assert empty.n_words == 3 and quantise(empty, np.zeros((0, 2), np.float32)).shape == (0,)


@pytest.mark.parametrize("kind", ["sift", "binary", "real", "one row", "all equal"])
def test_distinct_rows_are_numpys_unique_rows(kind):
    rng = np.random.default_rng(3)
    if kind == "sift":       # whole numbers, rows repeated, columns tied in places
        x = rng.integers(0, 4, (12, 128)).astype(np.float32)
        x = np.concatenate([x, x[[0, 5, 5]]])
    elif kind == "binary":
        x = rng.integers(0, 2, (40, 16)).astype(np.float32)
    elif kind == "real":
        x = rng.normal(size=(9, 32)).astype(np.float32)
        x[4] = x[2]
    elif kind == "one row":
        x = rng.normal(size=(1, 8)).astype(np.float32)
    else:
        x = np.ones((6, 64), np.float32)
    got = distinct_rows(x)
    want = np.unique(x, axis=0)
    assert got.dtype == want.dtype
    np.testing.assert_array_equal(got, want)
    known = {"sift": 12, "real": 8, "one row": 1, "all equal": 1}
    assert len(got) == known.get(kind, len(want))


def test_idf_known_answer():
    idf = inverse_document_frequency([np.array([0, 1, 1]), np.array([0]), np.array([0, 2])], 4)
    np.testing.assert_allclose(idf, [0.0, math.log(3), math.log(3), 0.0], rtol=1e-6)


def test_cluster_sums_equal_a_loop():
    rng = np.random.default_rng(9)
    x = rng.random((30, 4)).astype(np.float32)
    labels = rng.integers(0, 5, 30)
    expected = np.zeros((6, 4))
    for row, lab in zip(x, labels, strict=True):
        expected[lab] += row
    np.testing.assert_allclose(cluster_sums(x, labels, 6), expected, rtol=1e-6)


def test_vocabulary_shape_is_checked():
    with pytest.raises(ValueError, match="nodes"):
        Vocabulary(np.zeros((5, 2), np.float32), 2, 2, False, np.zeros(4, np.float32))
    with pytest.raises(ValueError, match="idf"):
        Vocabulary(np.zeros((6, 2), np.float32), 2, 2, False, np.zeros(3, np.float32))


def test_principal_axes_known_answer():
    # points on the line through (1, 2, 3) along (3, 4, 0) / 5, a little noise across it
    rng = np.random.default_rng(13)
    t = rng.uniform(-10, 10, 400)
    x = np.array([1.0, 2.0, 3.0]) + t[:, None] * np.array([0.6, 0.8, 0.0])
    x[:, 2] += 0.01 * rng.standard_normal(400)
    p = principal_axes([x[:200].astype(np.float32), x[200:].astype(np.float32)], 2,
                       rng=np.random.default_rng(0))
    assert p.shape == (3, 3) and p.dtype == np.float32
    np.testing.assert_allclose(p[0], x.mean(axis=0), atol=1e-4)
    np.testing.assert_allclose(p[1], [0.6, 0.8, 0.0], atol=1e-3)  # sign: largest positive
    np.testing.assert_allclose(p[1:] @ p[1:].T, np.eye(2), atol=1e-5)
    with pytest.raises(ValueError, match="n_components"):
        principal_axes([x.astype(np.float32)], 4, rng=np.random.default_rng(0))


def test_principal_axes_equal_the_covariance_loop():
    rng = np.random.default_rng(14)
    x = (rng.standard_normal((300, 4)) @ rng.standard_normal((4, 4))).astype(np.float32)
    p = principal_axes([x], 4, rng=np.random.default_rng(0))
    rows = x.astype(np.float64).tolist()
    mean = [sum(r[j] for r in rows) / len(rows) for j in range(4)]
    cov = [[sum((r[i] - mean[i]) * (r[j] - mean[j]) for r in rows) for j in range(4)]
           for i in range(4)]
    values = np.array([float(np.array(a) @ np.array(cov) @ np.array(a)) for a in p[1:]])
    assert (np.diff(values) <= 1e-3 * values[0]).all()  # largest variance first
    for a, lam in zip(p[1:].astype(np.float64), values, strict=True):  # eigenvectors
        np.testing.assert_allclose(np.array(cov) @ a, lam * a, rtol=1e-3, atol=1e-3 * values[0])


def test_projected_vocabulary():
    rng = np.random.default_rng(15)
    per_image = [rng.standard_normal((80, 6)).astype(np.float32) for _ in range(4)]
    vocab = train_vocabulary(per_image, branching=4, depth=1, binary=False, components=3,
                             rng=np.random.default_rng(1))
    assert (vocab.dim, vocab.word_dim) == (6, 3) and vocab.projection.shape == (4, 6)
    x = rng.standard_normal((5, 6)).astype(np.float32)
    mean, axes = vocab.projection[0].tolist(), vocab.projection[1:].tolist()
    slow = [[sum((v[j] - mean[j]) * a[j] for j in range(6)) for a in axes] for v in x.tolist()]
    np.testing.assert_allclose(vocab.project(x), slow, atol=1e-5)
    again = train_vocabulary(per_image, branching=4, depth=1, binary=False, components=3,
                             rng=np.random.default_rng(1))
    np.testing.assert_array_equal(again.projection, vocab.projection)
    np.testing.assert_array_equal(again.centroids, vocab.centroids)
    with pytest.raises(ValueError, match="vectors"):
        vocab.project(x[:, :3])
    with pytest.raises(ValueError, match="binary"):
        train_vocabulary(per_image, branching=2, depth=1, binary=True, components=3,
                         rng=np.random.default_rng(1))


class _Lazy:
    """A sequence that builds each image's vectors when read and counts reads."""

    def __init__(self, per_image):
        self.per_image, self.reads = per_image, 0

    def __len__(self):
        return len(self.per_image)

    def __getitem__(self, i):
        self.reads += 1
        return self.per_image[i].copy()


@pytest.mark.parametrize("max_training", [50, 10_000])
def test_sample_reads_images_one_at_a_time_and_draws_as_concatenating(max_training):
    rng = np.random.default_rng(4)
    per_image = [rng.random((int(k), 6)).astype(np.float32) for k in rng.integers(0, 30, 40)]
    # the obvious reference: every vector concatenated, then the same draw
    data = np.concatenate(per_image)
    ref_rng = np.random.default_rng(9)
    if len(data) > max_training:
        data = data[np.sort(ref_rng.choice(len(data), size=max_training, replace=False))]
    lazy = _Lazy(per_image)
    np.testing.assert_array_equal(_sample(lazy, np.random.default_rng(9), max_training), data)


def test_train_vocabulary_on_lazy_images_equals_lists():
    rng = np.random.default_rng(5)
    per_image = [rng.random((int(k), 16)).astype(np.float32) for k in rng.integers(5, 40, 60)]
    kwargs = dict(branching=4, depth=2, binary=False, components=8, max_training=500)
    eager = train_vocabulary(per_image, rng=np.random.default_rng(1), **kwargs)
    lazy = train_vocabulary(_Lazy(per_image), rng=np.random.default_rng(1), **kwargs)
    np.testing.assert_array_equal(lazy.centroids, eager.centroids)
    np.testing.assert_array_equal(lazy.idf, eager.idf)
    np.testing.assert_array_equal(lazy.projection, eager.projection)
    projected = Projected(per_image, eager.projection)
    np.testing.assert_allclose(projected[3], eager.project(per_image[3]), rtol=1e-6)


def test_distortion_is_the_squared_distance_to_the_word_in_the_vectors_own_space():
    rng = np.random.default_rng(11)
    per_image = [rng.random((80, 8)).astype(np.float32) for _ in range(4)]
    for components in (None, 3):
        vocab = train_vocabulary(per_image, branching=3, depth=2, binary=False,
                                 rng=np.random.default_rng(12), components=components)
        x = rng.random((25, 8)).astype(np.float32)
        words = _slow_quantise(vocab, vocab.project(x))
        expected = []
        for v, w in zip(x.tolist(), words, strict=True):
            if vocab.projection is None:
                back = vocab.words[w].tolist()
            else:  # the word taken back to the vectors' space along the principal axes
                back = (vocab.projection[0] + vocab.words[w] @ vocab.projection[1:]).tolist()
            expected.append(sum((a - b) ** 2 for a, b in zip(v, back, strict=True)))
        np.testing.assert_allclose(distortion(vocab, x), expected, rtol=1e-4, atol=1e-6)
    assert distortion(vocab, np.zeros((0, 8), np.float32)).shape == (0,)


def test_distortion_grows_for_vectors_unlike_the_training_ones():
    rng = np.random.default_rng(13)
    centres = rng.random((4, 6)) * 10
    vocab = train_vocabulary([_blobs(rng, centres, 40, 0.2)], branching=4, depth=1,
                             binary=False, rng=np.random.default_rng(14))
    alike = distortion(vocab, _blobs(rng, centres, 10, 0.2)).mean()
    unlike = distortion(vocab, _blobs(rng, centres + 3.0, 10, 0.2)).mean()
    assert alike < 0.5 and unlike > 10 * alike
