"""VLAD and bag-of-words descriptors: loop references and hand-computed answers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from vloc.workers.core.features.bow import bow
from vloc.workers.core.features.vlad import vlad
from vloc.workers.core.features.vocabulary import Vocabulary, quantise, train_vocabulary


def _flat(words, idf=None) -> Vocabulary:
    words = np.asarray(words, np.float32)
    idf = np.ones(len(words), np.float32) if idf is None else np.asarray(idf, np.float32)
    return Vocabulary(words, len(words), 1, False, idf)


def _slow_vlad(x: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """VLAD with loops: nearest centre, residual sums, intra, signed sqrt, L2."""
    k, dim = centres.shape
    blocks = [[0.0] * dim for _ in range(k)]
    for v in x.tolist():
        dist = [sum((a - b) ** 2 for a, b in zip(v, c, strict=True)) for c in centres.tolist()]
        w = dist.index(min(dist))
        for j in range(dim):
            blocks[w][j] += v[j] - float(centres[w, j])
    out = []
    for block in blocks:
        n = math.sqrt(sum(b * b for b in block))
        out += [math.copysign(math.sqrt(abs(b / n)), b) if n > 0 else 0.0 for b in block]
    total = math.sqrt(sum(o * o for o in out))
    return np.array([o / total for o in out] if total > 0 else out)


def _slow_bow(words: list[int], idf: list[float]) -> np.ndarray:
    tf = [words.count(w) / len(words) for w in range(len(idf))]
    v = [t * i for t, i in zip(tf, idf, strict=True)]
    n = math.sqrt(sum(a * a for a in v))
    return np.array([a / n for a in v])


def test_vlad_hand_computed():
    vocab = _flat([[0.0, 0.0], [10.0, 10.0]])
    x = np.array([[1.0, 0.0], [0.0, 2.0], [11.0, 10.0]], np.float32)
    # word 0: residuals (1, 0) + (0, 2) = (1, 2) -> /sqrt(5) -> signed sqrt
    # word 1: residual (1, 0) -> (1, 0) -> (1, 0)
    a, b = math.sqrt(1 / math.sqrt(5)), math.sqrt(2 / math.sqrt(5))
    expected = np.array([a, b, 1.0, 0.0])
    expected /= np.linalg.norm(expected)
    np.testing.assert_allclose(vlad(x, vocab), expected, rtol=1e-6)


def test_vlad_equals_the_loop_reference():
    rng = np.random.default_rng(0)
    train = [rng.standard_normal((40, 5)).astype(np.float32) for _ in range(3)]
    vocab = train_vocabulary(train, branching=6, depth=1, binary=False,
                             rng=np.random.default_rng(1))
    x = rng.standard_normal((25, 5)).astype(np.float32)
    v = vlad(x, vocab)
    assert v.shape == (30,) and v.dtype == np.float32
    np.testing.assert_allclose(v, _slow_vlad(x, vocab.words), atol=1e-6)
    assert np.linalg.norm(v) == pytest.approx(1.0, abs=1e-6)
    assert (v < 0).any()  # residuals are signed


def test_vlad_of_nothing_is_zero_and_checks_width():
    vocab = _flat([[0.0, 0.0], [1.0, 1.0]])
    np.testing.assert_array_equal(vlad(np.zeros((0, 2), np.float32), vocab), np.zeros(4))
    # every vector exactly on its centre: no residual anywhere
    np.testing.assert_array_equal(vlad(vocab.words.copy(), vocab), np.zeros(4))
    with pytest.raises(ValueError, match="vectors"):
        vlad(np.zeros((3, 5), np.float32), vocab)


def test_bow_hand_computed():
    vocab = _flat([[0.0], [10.0], [20.0]], idf=[math.log(3), 0.5, 0.0])
    x = np.array([[1.0], [2.0], [9.0], [21.0]], np.float32)  # words 0, 0, 1, 2
    raw = np.array([0.5 * math.log(3), 0.25 * 0.5, 0.0])
    np.testing.assert_allclose(bow(x, vocab), raw / np.linalg.norm(raw), rtol=1e-6)


def test_bow_equals_the_loop_reference():
    rng = np.random.default_rng(2)
    train = [(rng.random((40, 16)) < 0.5).astype(np.float32) for _ in range(5)]
    vocab = train_vocabulary(train, branching=3, depth=2, binary=True,
                             rng=np.random.default_rng(3))
    x = (rng.random((30, 16)) < 0.5).astype(np.float32)
    words = quantise(vocab, x).tolist()
    np.testing.assert_allclose(bow(x, vocab), _slow_bow(words, vocab.idf.tolist()), atol=1e-6)
    assert (bow(x, vocab) >= 0).all()


def test_bow_without_known_words_is_zero():
    vocab = _flat([[0.0], [10.0]], idf=[0.0, 1.0])
    np.testing.assert_array_equal(bow(np.array([[0.5]], np.float32), vocab), [0.0, 0.0])
    np.testing.assert_array_equal(bow(np.zeros((0, 1), np.float32), vocab), [0.0, 0.0])
