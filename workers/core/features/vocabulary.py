"""Visual vocabularies: hierarchical k-means (Nistér and Stewénius 2006) over a map's own
local features, with k-majority for binary descriptors (Grana et al. 2013).

A vocabulary is a complete tree of ``branching ** depth`` leaves (the words). Training splits
the descriptors into ``branching`` clusters by k-means, then each cluster again, ``depth``
levels down; a flat vocabulary of ``k`` words is the tree with ``branching = k, depth = 1``.
Quantising a descriptor descends the tree, comparing it with the ``branching`` children of its
current node at each level, so the cost grows with ``branching * depth``, not with the number
of words.

Binary descriptors (ORB) are trained as their 0/1 bit vectors (:func:`~.orb.unpack_bits`): the
squared Euclidean distance between two such vectors is their Hamming distance, so the
assignment step is the Hamming one, and k-majority's update sets each bit of a centre to the
majority vote of its members (the mean rounded; a tie gives 0), which keeps the centres binary.

Choices left open by the papers, and what is used here:

* Initialisation: k-means++ (Arthur and Vassilvitskii 2007) from the seeded ``rng``.
* A cluster left without members keeps its previous centre; training stops after
  ``iterations`` rounds or when no assignment changes.
* A node with fewer distinct training vectors than ``branching`` gets one child per vector
  and repeats the last for the remaining children: those words are never the nearest
  (ties go to the lowest index) and stay empty, the tree stays complete.
* An optional projection (PCA, as Jégou et al. 2012 reduce SIFT to 64 dimensions before
  VLAD) maps the local vectors to their first principal components before anything else:
  :func:`principal_axes` gives it, :meth:`Vocabulary.project` applies it, and the centres
  then live in the reduced space. The ORB bits and RootSIFT components are strongly
  correlated, so 64 components keep their structure at a fraction of the size.
* Words get inverse document frequencies ``log(N / n_w)`` from the N map images (``n_w``
  images contain word ``w``); a word no map image contains gets 0: it cannot tell map
  images apart.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

MAX_TRAINING: int = 60_000
"""Descriptors a vocabulary is trained on at most (a random sample of the map's)."""

ITERATIONS: int = 12
"""k-means rounds per node at most."""


@dataclass(frozen=True)
class Vocabulary:
    """A tree of cluster centres with the leaves' inverse document frequencies.

    Attributes
    ----------
    centroids : (n_nodes, P) float32 ndarray
        Every node below the root, level by level: level ``l`` (1-based) holds
        ``branching ** l`` nodes, and the children of node ``i`` of level ``l`` are nodes
        ``i * branching .. i * branching + branching - 1`` of level ``l + 1``. The last
        ``branching ** depth`` rows are the words.
    branching, depth : int
    binary : bool
        Trained by k-majority on bit vectors (centres are 0/1).
    idf : (n_words,) float32 ndarray
    projection : (P + 1, D) float32 ndarray or None
        The mean of the local vectors (row 0) and ``P`` orthonormal principal axes (rows
        1..P): vectors of dimension ``D`` are projected to ``P`` before quantisation. None:
        the centres live in the vectors' own space (``P = D``).
    """

    centroids: np.ndarray
    branching: int
    depth: int
    binary: bool
    idf: np.ndarray
    projection: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.branching < 1 or self.depth < 1:
            raise ValueError("branching and depth must be at least 1")
        n_nodes = sum(self.branching ** level for level in range(1, self.depth + 1))
        if self.centroids.ndim != 2 or self.centroids.shape[0] != n_nodes:
            raise ValueError(f"a tree of branching {self.branching} and depth {self.depth} "
                             f"has {n_nodes} nodes, got centroids of {self.centroids.shape}")
        if self.idf.shape != (self.n_words,):
            raise ValueError(f"idf must be ({self.n_words},), got {self.idf.shape}")
        if self.projection is not None and (
                self.projection.ndim != 2 or self.projection.shape[0] != self.word_dim + 1):
            raise ValueError(f"projection must be ({self.word_dim + 1}, D), "
                             f"got {self.projection.shape}")

    @property
    def n_words(self) -> int:
        return self.branching ** self.depth

    @property
    def dim(self) -> int:
        """D: the dimension of the local vectors the vocabulary takes."""
        if self.projection is not None:
            return int(self.projection.shape[1])
        return self.word_dim

    @property
    def word_dim(self) -> int:
        """P: the dimension of the centres (``dim`` without a projection)."""
        return int(self.centroids.shape[1])

    def project(self, vectors: np.ndarray) -> np.ndarray:
        """Local vectors in the centres' space: ``(K, D)`` -> ``(K, P)`` float32."""
        x = np.asarray(vectors, dtype=np.float32)
        if x.ndim != 2 or x.shape[1] != self.dim:
            raise ValueError(f"expected (K, {self.dim}) vectors for this vocabulary, "
                             f"got {x.shape}")
        if self.projection is None:
            return x
        return (x - self.projection[0]) @ self.projection[1:].T

    @property
    def words(self) -> np.ndarray:
        """(n_words, D) float32: the leaf centres."""
        return self.centroids[-self.n_words:]

    def level(self, level: int) -> np.ndarray:
        """(branching ** level, D) centres of one level (1-based)."""
        start = sum(self.branching ** j for j in range(1, level))
        return self.centroids[start:start + self.branching ** level]


def quantise(vocabulary: Vocabulary, vectors: np.ndarray) -> np.ndarray:
    """The word of each vector: descend the tree to the nearest child at every level.

    Parameters
    ----------
    vocabulary : Vocabulary
    vectors : (K, D) float32 ndarray
        Bit vectors for a binary vocabulary.

    Returns
    -------
    words : (K,) intp ndarray in ``0 .. n_words - 1``
    """
    return descend(vocabulary, np.asarray(vectors, dtype=np.float32), vocabulary.depth)


def descend(vocabulary: Vocabulary, x: np.ndarray, depth: int) -> np.ndarray:
    """Each row of ``x`` (in the centres' space) descended to level ``depth`` of the tree:
    its node's index within that level."""
    b = vocabulary.branching
    node = np.zeros(len(x), dtype=np.intp)
    if len(x) == 0:
        return node
    for level in range(1, depth + 1):
        centres = vocabulary.level(level)
        if level == 1:
            node = _nearest(x, centres)
            continue
        children = node[:, None] * b + np.arange(b)  # (K, b)
        c = centres[children]  # (K, b, D)
        # |x - c|^2 up to |x|^2, which is the same for every child of one vector
        d = np.einsum("kbd,kbd->kb", c, c) - 2.0 * np.einsum("kbd,kd->kb", c, x)
        node = children[np.arange(len(x)), d.argmin(axis=1)]
    return node


def train_vocabulary(per_image: list[np.ndarray], *, branching: int, depth: int,
                     binary: bool, rng: np.random.Generator, components: int | None = None,
                     max_training: int = MAX_TRAINING,
                     iterations: int = ITERATIONS) -> Vocabulary:
    """Train a vocabulary on the map images' local feature vectors.

    Parameters
    ----------
    per_image : list of (K_i, D) float32 ndarray
        Each map image's vectors (bit vectors when ``binary``); also give the idf.
    branching, depth : int
        ``branching ** depth`` words.
    binary : bool
        k-majority (centres rounded to 0/1) instead of k-means.
    rng : numpy.random.Generator
        Sampling and initialisation; the same seed gives the same vocabulary.
    components : int or None
        Project the vectors to this many principal components first (:func:`principal_axes`;
        not with ``binary``, whose centres are bit vectors).
    max_training : int
        Train on a random sample of at most this many vectors.

    Returns
    -------
    Vocabulary
    """
    projection = None
    if components is not None:
        if binary:
            raise ValueError("a binary vocabulary takes the bits themselves, not a projection")
        projection = principal_axes(per_image, components, rng=rng, max_training=max_training)
        per_image = Projected(per_image, projection)
    data = _sample(per_image, rng, max_training)
    dim = data.shape[1]
    levels = []
    members = [np.arange(len(data))]  # training vectors under each node of the level above
    for _ in range(depth):
        centres = np.empty((len(members) * branching, dim), np.float32)
        below = []
        for i, idx in enumerate(members):
            c, labels = _kmeans(data[idx], branching, binary=binary, rng=rng,
                                iterations=iterations)
            centres[i * branching:(i + 1) * branching] = c
            below += [idx[labels == j] for j in range(branching)]
        levels.append(centres)
        members = below
    centroids = np.concatenate(levels)
    vocab = Vocabulary(centroids, branching, depth, binary, np.zeros(branching ** depth, np.float32))
    return Vocabulary(centroids, branching, depth, binary,
                      inverse_document_frequency([quantise(vocab, v) for v in per_image],
                                                 vocab.n_words), projection)


def principal_axes(per_image: list[np.ndarray], n_components: int, *,
                   rng: np.random.Generator, max_training: int = MAX_TRAINING) -> np.ndarray:
    """Mean and leading principal axes of the map images' local vectors.

    Parameters
    ----------
    per_image : list of (K_i, D) float32 ndarray
    n_components : int
        P, at most D.
    rng : numpy.random.Generator
        Draws the sample when there are more than ``max_training`` vectors.

    Returns
    -------
    projection : (P + 1, D) float32 ndarray
        Row 0 the mean, rows 1..P the eigenvectors of the covariance with the largest
        eigenvalues, largest first, each with its largest component positive (an
        eigenvector's sign is arbitrary; this fixes it).
    """
    x = _sample(per_image, rng, max_training).astype(np.float64)
    dim = x.shape[1]
    if not 1 <= n_components <= dim:
        raise ValueError(f"n_components must be in 1..{dim}, got {n_components}")
    mean = x.mean(axis=0) if len(x) else np.zeros(dim)
    centred = x - mean
    _, vectors = np.linalg.eigh(centred.T @ centred)
    axes = vectors[:, ::-1][:, :n_components].T  # eigh sorts ascending
    flip = np.sign(axes[np.arange(n_components), np.abs(axes).argmax(axis=1)])
    axes *= np.where(flip == 0, 1.0, flip)[:, None]
    return np.vstack([mean, axes]).astype(np.float32)


class Projected(Sequence):
    """Each image's vectors projected onto principal axes, computed when read.

    A large map's projected vectors would not fit in memory at once; each pass over the
    images (sampling, the idf) reads them one image at a time.

    Parameters
    ----------
    per_image : sequence of (K_i, D) float ndarray
    projection : (P + 1, D) float32 ndarray
        As :func:`principal_axes` gives it.
    """

    def __init__(self, per_image, projection: np.ndarray) -> None:
        self.per_image = per_image
        self.projection = projection

    def __len__(self) -> int:
        return len(self.per_image)

    def __getitem__(self, i: int) -> np.ndarray:
        v = np.asarray(self.per_image[i], np.float32)
        return (v - self.projection[0]) @ self.projection[1:].T

    def counts(self) -> np.ndarray:
        """(N,) int: vectors per image, without projecting them."""
        return vector_counts(self.per_image)


def vector_counts(per_image) -> np.ndarray:
    """Vectors per image: the sequence's own ``counts()`` where it has one (lazy
    sequences count without computing the vectors), else the lengths of its arrays."""
    counts = getattr(per_image, "counts", None)
    if counts is not None:
        return np.asarray(counts(), np.int64)
    return np.array([len(v) for v in per_image], np.int64)


def _sample(per_image, rng: np.random.Generator, max_training: int) -> np.ndarray:
    """All vectors of all images, or a random sample of ``max_training`` (in image order).

    The sample's indices are drawn from the per-image counts and each image is read once
    to gather its share: the map's vectors are never concatenated whole.
    """
    counts = vector_counts(per_image)
    total = int(counts.sum())
    chosen = None
    if total > max_training:
        chosen = np.sort(rng.choice(total, size=max_training, replace=False))
    starts = np.concatenate([[0], np.cumsum(counts)])
    parts, dims = [], set()
    for i in range(len(counts)):
        v = per_image[i]
        if np.ndim(v) == 2:
            dims.add(v.shape[1])
        if chosen is None:
            parts.append(np.asarray(v, np.float32))
            continue
        lo, hi = np.searchsorted(chosen, [starts[i], starts[i + 1]])
        if hi > lo:
            parts.append(np.asarray(v, np.float32)[chosen[lo:hi] - starts[i]])
    if len(dims) != 1:
        raise ValueError(f"expected a list of (K_i, D) arrays of one width D, got widths {dims}")
    return np.concatenate(parts) if parts else np.zeros((0, dims.pop()), np.float32)


def inverse_document_frequency(words_per_image: list[np.ndarray], n_words: int) -> np.ndarray:
    """``log(N / n_w)`` for each word; 0 for words in no image.

    Parameters
    ----------
    words_per_image : list of (K_i,) int ndarray
    n_words : int

    Returns
    -------
    idf : (n_words,) float32 ndarray
    """
    n_images = len(words_per_image)
    df = np.zeros(n_words, dtype=np.int64)
    for words in words_per_image:
        df[np.unique(np.asarray(words, dtype=np.intp))] += 1
    idf = np.zeros(n_words, dtype=np.float64)
    seen = df > 0
    idf[seen] = np.log(n_images / df[seen])
    return idf.astype(np.float32)


def _nearest(x: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Index of the nearest centre of each row (squared Euclidean; ties to the lowest)."""
    d = x @ centres.T  # (K, k)
    d *= -2.0
    d += np.einsum("kd,kd->k", centres, centres)[None, :]
    return d.argmin(axis=1)


def distinct_rows(x: np.ndarray) -> np.ndarray:
    """The distinct rows of ``x``, in lexicographic order: ``np.unique(x, axis=0)`` for
    finite values. NumPy's version sorts the rows as records of one field per column, and
    building that record type costs about a millisecond per call for descriptors of 128 to
    256 columns, however few the rows: a tree's small leaves took a tenth of a ten-image
    map's build in it."""
    x = np.asarray(x)
    if len(x) < 2:
        return x.copy()
    ordered = x[np.lexsort(x.T[::-1])]
    keep = np.ones(len(ordered), dtype=bool)
    keep[1:] = (ordered[1:] != ordered[:-1]).any(axis=1)
    return ordered[keep]


def _kmeans(x: np.ndarray, k: int, *, binary: bool, rng: np.random.Generator,
            iterations: int) -> tuple[np.ndarray, np.ndarray]:
    """k centres of ``x`` (k-majority when ``binary``) and each row's cluster."""
    dim = x.shape[1]
    if len(x) == 0:
        return np.zeros((k, dim), np.float32), np.zeros(0, np.intp)
    if len(x) <= k:
        # one centre per distinct vector; the rest repeat the last and stay empty
        distinct = distinct_rows(x)
        centres = distinct[np.minimum(np.arange(k), len(distinct) - 1)].astype(np.float32)
        return centres, _nearest(x, centres)
    centres = _kmeans_pp(x, k, rng)
    labels = _nearest(x, centres)
    for _ in range(iterations):
        counts = np.bincount(labels, minlength=k)
        sums = cluster_sums(x, labels, k)
        filled = counts > 0
        means = sums[filled] / counts[filled, None]
        centres = centres.copy()
        centres[filled] = (means > 0.5) if binary else means
        new = _nearest(x, centres)
        if np.array_equal(new, labels):
            break
        labels = new
    return centres, labels


_DENSE_MEMBERS = 1 << 20
"""Largest membership matrix (entries) :func:`cluster_sums` builds dense."""


def cluster_sums(x: np.ndarray, labels: np.ndarray, k: int) -> np.ndarray:
    """Sum of the rows of ``x`` in each of ``k`` clusters: ``(k, D)`` float64.

    One product of the ``(k, K)`` membership matrix with ``x``: dense for one image's
    features (building a sparse matrix costs more than the product), sparse for training.
    """
    from scipy.sparse import csr_matrix

    labels = np.asarray(labels, dtype=np.intp)
    if k * len(labels) <= _DENSE_MEMBERS:
        dense = (labels[None, :] == np.arange(k)[:, None]).astype(np.float32)
        return np.asarray(dense @ np.asarray(x, dtype=np.float32), dtype=np.float64)
    members = csr_matrix((np.ones(len(labels), np.float32), (labels, np.arange(len(labels)))),
                         shape=(k, len(labels)))
    return np.asarray(members @ np.asarray(x, dtype=np.float32), dtype=np.float64)


def _kmeans_pp(x: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """k-means++ seeding: each next centre drawn with probability ~ squared distance."""
    centres = np.empty((k, x.shape[1]), np.float32)
    centres[0] = x[rng.integers(len(x))]
    sq = np.einsum("kd,kd->k", x, x)
    closest = np.maximum(sq - 2.0 * (x @ centres[0]) + centres[0] @ centres[0], 0.0)
    for i in range(1, k):
        total = float(closest.sum())
        j = rng.choice(len(x), p=closest / total) if total > 0 else rng.integers(len(x))
        centres[i] = x[j]
        d = np.maximum(sq - 2.0 * (x @ centres[i]) + centres[i] @ centres[i], 0.0)
        np.minimum(closest, d, out=closest)
    return centres
