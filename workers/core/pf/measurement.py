"""Measurement models: what was measured -> a log-likelihood per particle.

Each kind of measurement is an object with a ``kind`` name and a :meth:`likelihood` method
(:class:`Measurement`); a filter step takes one or more and adds their log-likelihoods, so
independent measurements of one frame multiply. Weights are computed in the log domain so
that a power of 20 cannot underflow.

:class:`ImageSimilarity`, Weiss et al. 2008, IV-A step 3: a particle's weight is the
similarity between the frame and its nearest map image, times a factor that decreases with
the particle's distance to that image; global similarities are raised to the 20th power
because their differences are small ("but still distinctive at that low level").
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from scipy.spatial import cKDTree

SimilarityFn = Callable[[np.ndarray], np.ndarray]
"""Map-image indexes (k,) -> similarities (k,) in [0, 1] of the current frame."""


@dataclass(frozen=True)
class Likelihood:
    """What one measurement said about the particles.

    Attributes
    ----------
    kind : str
        The measurement's kind.
    log : (m,) float64 ndarray
        Log-likelihood of each particle (``-inf``: impossible).
    scored : (k,) int ndarray
        Map images the measurement compared the frame with (empty for kinds that compare
        none); replacement particles may start near them.
    similarities : (k,) float64 ndarray
        Their similarities to the frame, in [0, 1].
    power : float
        Exponent the similarities were raised to.
    nearest : (m,) int ndarray or None
        Each particle's nearest map image, where the measurement looked them up.
    """

    kind: str
    log: np.ndarray
    scored: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    similarities: np.ndarray = field(default_factory=lambda: np.zeros(0))
    power: float = 1.0
    nearest: np.ndarray | None = None


class Measurement(Protocol):
    """One kind of measurement of the current frame."""

    kind: str

    def likelihood(self, xy: np.ndarray, tree: cKDTree) -> Likelihood:
        """Log-likelihoods of particles at ``xy`` (m, 2); ``tree`` indexes the map images."""


def distance_factor(d: np.ndarray, scale: float) -> np.ndarray:
    """``exp(-d^2 / (2 scale^2))``: 1 on a map image, falling off over ``scale`` metres."""
    return np.exp(-0.5 * (d / scale) ** 2)


def log_likelihoods(similarity: np.ndarray, distances: np.ndarray, *, power: float,
                    scale: float) -> np.ndarray:
    """Log of ``similarity ** power * distance_factor`` per particle.

    Parameters
    ----------
    similarity : (m,) float ndarray in [0, 1]
        Similarity of the frame with each particle's nearest map image.
    distances : (m,) float ndarray
        Distance (m) of each particle to that image.
    power : float
        20 for global features, 1 for SIFT.
    scale : float
        Length scale of the distance factor (m).

    Returns
    -------
    (m,) float64 ndarray; ``-inf`` where the similarity is zero.
    """
    with np.errstate(divide="ignore"):
        log_s = np.log(np.clip(similarity, 0.0, 1.0))
    return power * log_s - 0.5 * (distances / scale) ** 2


def normalise_log(logw: np.ndarray) -> np.ndarray | None:
    """Normalised weights from log weights, or None when every weight is zero."""
    top = np.max(logw)
    if not np.isfinite(top):
        return None
    w = np.exp(logw - top)
    return w / w.sum()


@dataclass(frozen=True)
class ImageSimilarity:
    """The frame's similarity with each particle's nearest map image (Weiss IV-A step 3).

    Similarities are computed once per distinct map image.

    Attributes
    ----------
    kind : str
        Feature type the similarity uses (``"global"`` or ``"sift"``).
    similarity : callable
        Map-image indexes -> similarities in [0, 1] of the current frame.
    power : float
        Exponent of the similarities.
    scale : float
        Length scale (m) of the distance factor.
    every_image : bool
        Score every map image (cheap for global features), so replacement particles can
        start at the best retrieved images.
    candidates : (c,) int ndarray or None
        Further map images to score besides the particles' nearest ones (e.g. the best
        global matches, shortlisted for SIFT).
    """

    kind: str
    similarity: SimilarityFn
    power: float
    scale: float
    every_image: bool = False
    candidates: np.ndarray | None = None

    def likelihood(self, xy: np.ndarray, tree: cKDTree) -> Likelihood:
        dist, nearest = tree.query(xy)
        if self.every_image:
            scored = np.arange(tree.n)
            sims = np.asarray(self.similarity(scored), dtype=np.float64)
            per_particle = sims[nearest]
        else:
            scored = np.unique(nearest if self.candidates is None
                               else np.concatenate([nearest, self.candidates]))
            sims = np.asarray(self.similarity(scored), dtype=np.float64)
            per_particle = sims[np.searchsorted(scored, nearest)]
        log = log_likelihoods(per_particle, dist, power=self.power, scale=self.scale)
        return Likelihood(self.kind, log, scored, sims, self.power, nearest)


def position_log_likelihoods(xy: np.ndarray, position: np.ndarray, sigma: float, *,
                             outlier: float) -> np.ndarray:
    """Log-likelihood of a metric position measurement for each particle.

    A Gaussian of ``sigma`` metres per axis around the measured position, mixed with a
    constant floor: with probability ``outlier`` the measurement is wrong (a pose solved on
    the wrong place), and then it says nothing about the particle. The floor keeps one bad
    registration from wiping out a cloud that is right.

    Parameters
    ----------
    xy : (m, 2) float ndarray
    position : (2,) float ndarray
    sigma : float
    outlier : float in (0, 1)

    Returns
    -------
    (m,) float64 ndarray
    """
    d2 = np.sum((np.asarray(xy, np.float64) - np.asarray(position, np.float64)) ** 2, axis=1)
    return np.log((1.0 - outlier) * np.exp(-0.5 * d2 / sigma ** 2) + outlier)


@dataclass(frozen=True)
class Position:
    """A metric position of the frame: a solved camera pose, or a position between the best
    verified map images (:mod:`workers.core.localisers.refine`).

    Attributes
    ----------
    kind : str
        ``"registered"`` or ``"interpolated"``.
    xy : (2,) float ndarray
    sigma : float
        Standard deviation per axis (m).
    outlier : float
        Probability that the position is wrong.
    alone : bool
        The position replaces the frame's image similarity in the weights instead of
        multiplying it: a global step's fix, registered against the images its global
        features ranked, is far sharper than those features, whose likelihood would only
        pull the estimate towards the images they confused.
    """

    kind: str
    xy: np.ndarray
    sigma: float
    outlier: float
    alone: bool = False

    def likelihood(self, xy: np.ndarray, tree: cKDTree) -> Likelihood:
        return Likelihood(self.kind, position_log_likelihoods(xy, self.xy, self.sigma,
                                                              outlier=self.outlier))
