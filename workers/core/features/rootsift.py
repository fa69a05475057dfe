"""RootSIFT: SIFT descriptors compared under the Hellinger kernel (Arandjelović and
Zisserman 2012, "Three things everyone should know to improve object retrieval").

Each SIFT descriptor is L1-normalised and square-rooted element-wise; the Euclidean distance
between two RootSIFT vectors is then the Hellinger distance between the original histograms,
which weighs the many small bins of a gradient histogram against its few large ones better
than the Euclidean distance does. The result has unit L2 norm.
"""

from __future__ import annotations

import numpy as np

DIM: int = 128


def rootsift(descriptors: np.ndarray) -> np.ndarray:
    """RootSIFT vectors of SIFT descriptors.

    Parameters
    ----------
    descriptors : (K, 128) uint8 or float ndarray, non-negative

    Returns
    -------
    root : (K, 128) float32 ndarray
        ``sqrt(d / sum(d))`` per row, of unit L2 norm; an all-zero descriptor stays zero.
    """
    d = np.asarray(descriptors, dtype=np.float32)
    if d.ndim != 2 or d.shape[1] != DIM:
        raise ValueError(f"expected (K, {DIM}) SIFT descriptors, got {d.shape}")
    if d.size and d.min() < 0:
        raise ValueError("SIFT descriptors must be non-negative")
    total = d.sum(axis=1, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        scaled = np.where(total > 0, d / total, 0.0).astype(np.float32)
    return np.sqrt(scaled)
