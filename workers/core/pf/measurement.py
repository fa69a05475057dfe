"""The measurement model: image similarities -> particle weights.

Weiss et al. 2008, IV-A step 3: a particle's weight is the similarity between the frame and
its nearest map image, times a factor that decreases with the particle's distance to that
image; global similarities are raised to the 20th power because their differences are small
("but still distinctive at that low level"). Weights are computed in the log domain so the
power cannot underflow.
"""

from __future__ import annotations

import numpy as np


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


def position_log_likelihoods(xy: np.ndarray, position: np.ndarray, sigma: float, *,
                             outlier: float) -> np.ndarray:
    """Log-likelihood of a metric position measurement for each particle.

    A Gaussian of ``sigma`` metres per axis around the measured position, mixed with a
    constant floor: with probability ``outlier`` the measurement is wrong (a pose solved
    on the wrong place), and then it says nothing about the particle. The floor keeps one
    bad registration from wiping out a cloud that is right.

    Parameters
    ----------
    xy : (m, 2) float ndarray
        Particle positions.
    position : (2,) float ndarray
    sigma : float
    outlier : float in [0, 1)

    Returns
    -------
    (m,) float64 ndarray
    """
    d2 = np.sum((np.asarray(xy, np.float64) - np.asarray(position, np.float64)) ** 2, axis=1)
    gauss = np.exp(-0.5 * d2 / sigma ** 2)
    return np.log((1.0 - outlier) * gauss + outlier)
