"""Bag of visual words with tf-idf weights (Sivic and Zisserman 2003; Nistér and Stewénius
2006).

An image's local feature vectors are quantised into the words of a vocabulary; the
descriptor holds, per word, its term frequency (occurrences / vectors in the image) times the
word's inverse document frequency over the map images, scaled to unit L2 norm. Two
descriptors are compared by their dot product (cosine). All components are non-negative, and
most are zero: against a map the score is a sum over the words the frame contains, which is
what an inverted index computes; at a few hundred to a few thousand words the dense
``(N, n_words)`` matrix is as fast and simpler.
"""

from __future__ import annotations

import numpy as np

from .vocabulary import Vocabulary, quantise


def bow(vectors: np.ndarray, vocabulary: Vocabulary, *,
        words: np.ndarray | None = None) -> np.ndarray:
    """tf-idf bag-of-words descriptor of one image.

    Parameters
    ----------
    vectors : (K, P) float32 ndarray
        The image's local feature vectors in the vocabulary's space
        (:meth:`Vocabulary.project`; bit vectors for a binary vocabulary).
    vocabulary : Vocabulary
    words : (K,) int ndarray, optional
        The vectors' words, when already quantised.

    Returns
    -------
    descriptor : (n_words,) float32 ndarray
        Non-negative, unit L2 norm; all zeros for an image without local features or whose
        words no map image contains.
    """
    x = np.asarray(vectors, dtype=np.float32)
    if x.ndim != 2 or x.shape[1] != vocabulary.word_dim:
        raise ValueError(f"expected (K, {vocabulary.word_dim}) vectors for this vocabulary, "
                         f"got {x.shape}")
    if words is None:
        words = quantise(vocabulary, x)
    n = vocabulary.n_words
    if len(words) == 0:
        return np.zeros(n, np.float32)
    v = np.bincount(words, minlength=n) / len(words) * vocabulary.idf.astype(np.float64)
    total = float(np.sqrt(v @ v))
    if total <= 0.0:
        return np.zeros(n, np.float32)
    return (v / total).astype(np.float32)
