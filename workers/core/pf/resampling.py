"""Resamplers: pure functions from normalised weights to particle indexes."""

from __future__ import annotations

import numpy as np


def multinomial(weights: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Draw ``len(weights)`` indexes independently with probability ``weights``.

    Weiss et al. 2008, IV-A step 1: "randomly draw m particles according to the weights".

    Parameters
    ----------
    weights : (m,) float ndarray, non-negative, summing to 1
    rng : numpy.random.Generator

    Returns
    -------
    indexes : (m,) int64 ndarray
    """
    cdf = np.cumsum(weights)
    cdf[-1] = 1.0  # guard against round-off leaving the last bin short
    return np.searchsorted(cdf, rng.random(len(weights)), side="right").astype(np.int64)


def systematic(weights: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Systematic resampling: one random offset, m evenly spaced pointers.

    Lower variance than multinomial; each particle is drawn ``floor(m w)`` or
    ``ceil(m w)`` times.
    """
    m = len(weights)
    cdf = np.cumsum(weights)
    cdf[-1] = 1.0
    pointers = (rng.random() + np.arange(m)) / m
    return np.searchsorted(cdf, pointers, side="right").astype(np.int64)


RESAMPLERS = {"multinomial": multinomial, "systematic": systematic}
