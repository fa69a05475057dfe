"""VLAD: vectors of locally aggregated descriptors (Jégou et al. 2010), intra-normalised
(Arandjelović and Zisserman 2013) and power-normalised (Jégou et al. 2012).

Each local feature vector ``x`` is assigned to its nearest word ``c`` of a vocabulary; the
image's descriptor concatenates, per word, the sum of the residuals ``x - c`` of the vectors
assigned to it. Then:

1. intra-normalisation: each word's block is scaled to unit L2 norm, so that a few bursty
   words (a repeated texture: crop rows, a tiled roof) cannot dominate the whole vector;
   a block without vectors stays zero;
2. power normalisation: every component ``v`` becomes ``sign(v) sqrt(|v|)``;
3. the whole vector is scaled to unit L2 norm.

Two descriptors are compared by their dot product, the cosine (``cosine`` measure of
:mod:`workers.core.measures`). Components are signed.
"""

from __future__ import annotations

import numpy as np

from .vocabulary import Vocabulary, cluster_sums, quantise


def vlad(vectors: np.ndarray, vocabulary: Vocabulary, *,
         words: np.ndarray | None = None) -> np.ndarray:
    """VLAD descriptor of one image.

    Parameters
    ----------
    vectors : (K, P) float32 ndarray
        The image's local feature vectors in the vocabulary's space
        (:meth:`Vocabulary.project`).
    vocabulary : Vocabulary
        Its words (leaves) are the centres; a flat vocabulary (``depth = 1``) is usual.
    words : (K,) int ndarray, optional
        The vectors' words, when already quantised.

    Returns
    -------
    descriptor : (n_words * P,) float32 ndarray
        Unit L2 norm; all zeros for an image without local features.
    """
    x = np.asarray(vectors, dtype=np.float32)
    centres = vocabulary.words
    k, dim = centres.shape
    if x.ndim != 2 or x.shape[1] != dim:
        raise ValueError(f"expected (K, {dim}) vectors for this vocabulary, got {x.shape}")
    if words is None:
        words = quantise(vocabulary, x)
    counts = np.bincount(words, minlength=k).astype(np.float64)
    residuals = cluster_sums(x, words, k) - counts[:, None] * centres
    norms = np.sqrt(np.einsum("kd,kd->k", residuals, residuals))
    residuals[norms > 0] /= norms[norms > 0, None]
    v = np.sign(residuals) * np.sqrt(np.abs(residuals))
    total = float(np.sqrt(np.einsum("kd,kd->", v, v)))
    if total <= 0.0:
        return np.zeros(k * dim, np.float32)
    return (v / total).astype(np.float32).ravel()
