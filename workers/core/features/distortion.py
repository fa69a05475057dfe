"""How well a vocabulary fits images: the distortion of their local vectors against it, and
the fit a map records of it for each of its images (:mod:`workers.core.carryover` reads it
to keep a map's vocabularies through an update or train them again)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .vocabulary import Vocabulary, descend


def distortion(vocabulary: Vocabulary, vectors: np.ndarray, *,
               level: int | None = None) -> np.ndarray:
    """How far each local vector lies from the vocabulary: its squared distance to its
    node at ``level`` of the tree (the words by default), in the vectors' own space (a
    projection's residual, what the principal axes leave out, included).

    Parameters
    ----------
    vocabulary : Vocabulary
    vectors : (K, D) ndarray
        Local vectors in the vocabulary's input space (bit vectors for a binary one).
    level : int, optional
        1 .. ``depth``; the descent stops there.

    Returns
    -------
    (K,) float64 ndarray
    """
    x = np.asarray(vectors, dtype=np.float32)
    p = vocabulary.project(x)
    if len(x) == 0:
        return np.zeros(0)
    level = vocabulary.depth if level is None else level
    if not 1 <= level <= vocabulary.depth:
        raise ValueError(f"level must be in 1..{vocabulary.depth}, got {level}")
    nodes = descend(vocabulary, p, level)
    off = p.astype(np.float64) - vocabulary.level(level)[nodes]
    d = np.einsum("kd,kd->k", off, off)
    if vocabulary.projection is not None:
        centred = x.astype(np.float64) - vocabulary.projection[0]
        kept = p.astype(np.float64)
        d += np.maximum(np.einsum("kd,kd->k", centred, centred)
                        - np.einsum("kd,kd->k", kept, kept), 0.0)
    return d


FIT_NODES: int = 64
"""A vocabulary's fit is measured at the deepest level of its tree with at most this many
nodes (:func:`fit_level`)."""


def fit_level(vocabulary: Vocabulary) -> int:
    """The level of ``vocabulary``'s tree its fit is measured at: the deepest with at most
    :data:`FIT_NODES` nodes (the first where even that has more).

    The words of a fine tree (4,096 of them over a small map's 20,000 vectors) sit close to
    the very vectors they were trained on, so any image they were not trained on lies
    farther from them, however alike: its distortion there says more about the training
    than about the image. A few dozen nodes, each trained on hundreds of vectors, are as
    near to a new image of the same scenes as to the trained ones, and move away from
    images unlike them."""
    level = 1
    while level < vocabulary.depth and vocabulary.branching ** (level + 1) <= FIT_NODES:
        level += 1
    return level


@dataclass(frozen=True)
class VocabularyFit:
    """How well a vocabulary fits the images it describes (:func:`distortion`), and which
    of them it was trained on.

    Attributes
    ----------
    trained : float
        The mean of ``images`` over the images it was trained on, when it was trained.
    images : (N,) float32 ndarray
        Each image's mean distortion (0 for an image without local vectors).
    revision : int
        The map revision that trained the vocabulary.
    trained_on : (N,) bool ndarray or None
        Whether each image was among those it was trained on (and gave the idf); None:
        all of them.
    """

    trained: float
    images: np.ndarray
    revision: int = 0
    trained_on: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.trained_on is not None and np.shape(self.trained_on) != np.shape(self.images):
            raise ValueError("trained_on must have one entry per image")

    def rise(self) -> float:
        """How much the images' mean distortion has risen over the trained images' (a
        fraction): what images described since training have added."""
        if len(self.images) == 0 or self.trained <= 0:
            return 0.0
        return float(np.mean(self.images, dtype=np.float64) / self.trained - 1.0)

    def untrained_share(self) -> float:
        """The share of the images the vocabulary was not trained on."""
        if self.trained_on is None or len(self.images) == 0:
            return 0.0
        return float(1.0 - np.mean(self.trained_on))


def image_distortion(vocabulary: Vocabulary, vectors: np.ndarray) -> float:
    """One image's mean :func:`distortion` at the :func:`fit_level` (0 without local
    vectors)."""
    d = distortion(vocabulary, vectors, level=fit_level(vocabulary))
    return float(d.mean()) if len(d) else 0.0
