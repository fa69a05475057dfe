"""The particle cloud's clusters, and the position a multimodal cloud reports.

A cloud that is unsure where the platform is holds several hypotheses at once: a dense
cluster where a metric fix put most of the weight, and particles spread over look-alike
places that keep a little. The weighted mean of the whole cloud (Weiss et al. 2008, IV-A
step 4) then lies between the hypotheses, where none of the weight is: on seneca-uav a
fix 4.6 m from the truth, holding 86 % of the weight, was reported 18 m off because the
rest of the cloud lay hundreds of metres away. nav2's AMCL reports the mean of its heaviest
cluster instead (its particles binned in a histogram, occupied neighbouring bins joined);
:func:`heaviest_cluster` does the same in the plane, and says how much of the weight the
cluster holds: a filter reports it where it holds most (:class:`~.filter.ParticleFilter`),
and judges that cluster's spread rather than the strays'. Where no cluster does, the cloud
has no hypothesis it prefers and the whole mean hedges between them: on seneca-uav,
reporting the heaviest cluster always cost the `sift` mode 0.4 m of mean error (6.4 -> 6.8
m), and only where it holds most, nothing.
"""

from __future__ import annotations

import numpy as np


def cluster_labels(xy: np.ndarray, cell_m: float) -> np.ndarray:
    """Each particle's cluster: particles binned in square cells of ``cell_m`` metres, and
    occupied cells that touch (side or corner) joined into one cluster.

    Two particles less than ``cell_m`` apart always share a cluster; two more than
    ``2 * sqrt(2) * cell_m`` apart share one only through particles between them.

    Parameters
    ----------
    xy : (m, 2) float ndarray
    cell_m : float, > 0

    Returns
    -------
    (m,) int ndarray
        Cluster numbers from 0, in the order of each cluster's first cell by its east, then
        north, coordinate (a cloud of one cluster is all 0).
    """
    if not cell_m > 0:
        raise ValueError(f"cell_m must be positive, not {cell_m}")
    cells = np.floor(np.asarray(xy, np.float64) / cell_m).astype(np.int64)
    # one integer per cell, east-major, with an empty row of cells on every side so that
    # a neighbour's key never wraps onto another column's cell
    cells -= cells.min(axis=0) - 1
    rows = int(cells[:, 1].max()) + 2
    occupied, inverse = np.unique(cells[:, 0] * rows + cells[:, 1], return_inverse=True)
    n = len(occupied)
    # each touching pair once: the neighbours east, north, north-east and south-east
    src, dst = [], []
    for step in (rows, 1, rows + 1, rows - 1):
        at = np.searchsorted(occupied, occupied + step)
        hit = at < n
        hit[hit] = occupied[at[hit]] == occupied[hit] + step
        src.append(np.flatnonzero(hit))
        dst.append(at[hit])
    src, dst = np.concatenate(src), np.concatenate(dst)
    # every cell takes the lowest cell number among its neighbours, then its label's
    # label, until the touching cells agree: each cluster is labelled by its first cell
    label = np.arange(n)
    while True:
        low = np.minimum(label[src], label[dst])
        lower = label.copy()
        np.minimum.at(lower, src, low)
        np.minimum.at(lower, dst, low)
        lower = lower[lower]
        if np.array_equal(lower, label):
            break
        label = lower
    _, cluster = np.unique(label, return_inverse=True)
    return cluster[np.ravel(inverse)]


def heaviest_cluster(xy: np.ndarray, w: np.ndarray, cell_m: float) -> tuple[np.ndarray, float]:
    """The cloud's heaviest cluster (:func:`cluster_labels`) and the share of the weight it
    holds.

    Parameters
    ----------
    xy : (m, 2) float ndarray
    w : (m,) float ndarray, non-negative, not all zero
    cell_m : float

    Returns
    -------
    members : (m,) bool ndarray
        Its particles. Where two clusters weigh the same, the first in
        :func:`cluster_labels`' order.
    share : float
        Its weight over the whole cloud's, in (0, 1].
    """
    w = np.asarray(w, np.float64)
    labels = cluster_labels(xy, cell_m)
    mass = np.bincount(labels, weights=w)
    best = int(np.argmax(mass))
    return labels == best, float(mass[best] / mass.sum())
