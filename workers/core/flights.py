"""A map's flights: its images grouped by when they were taken.

A map may hold several flights over the same ground (a survey flown again weeks later, in
other light or season). A flight is a run of captures with no gap longer than
:data:`FLIGHT_GAP_S` between consecutive ones; images without a capture time belong to none.
Flights flown at the same time by several platforms fall into one.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

FLIGHT_GAP_S: float = 30 * 60.0
"""A pause without captures longer than this (s) ends a flight: a battery change takes
minutes, a second survey of the same ground hours or weeks."""


def flight_labels(captured_at, gap_s: float = FLIGHT_GAP_S) -> np.ndarray:
    """Each image's flight, numbered 0, 1, ... in time order; -1 for an untimed image.

    Parameters
    ----------
    captured_at : (n,) float array-like
        Capture times (s since the epoch), NaN where unknown.
    gap_s : float
        The longest pause within one flight.

    Returns
    -------
    (n,) int64 ndarray
    """
    t = np.asarray(captured_at, np.float64).reshape(-1)
    labels = np.full(len(t), -1, np.int64)
    timed = np.flatnonzero(np.isfinite(t))
    if not len(timed):
        return labels
    order = timed[np.argsort(t[timed], kind="stable")]
    starts = np.concatenate([[0], np.diff(t[order]) > gap_s]).astype(np.int64)
    labels[order] = np.cumsum(starts)
    return labels


def flight_spacing(positions, captured_at=None) -> float:
    """A survey's spacing (m): the median distance from each image to the nearest other
    image of its own flight.

    A second flight over the same ground (the same waypoints flown again) puts an image of
    the other flight within metres of each one, or on top of it: the spacing over every
    image would shrink to that, and whatever is sized by it (how far apart tie points are
    matched, how far a particle's likelihood reaches) with it. Untimed images count as one
    flight; where no flight holds two images, every image is measured against every other.
    Returns 1.0 for fewer than two images.
    """
    xy = np.asarray(positions, np.float64).reshape(-1, 2)
    if len(xy) < 2:
        return 1.0
    labels = (np.full(len(xy), -1, np.int64) if captured_at is None
              else flight_labels(captured_at))
    gaps = []
    for label in np.unique(labels):
        mine = xy[labels == label]
        if len(mine) >= 2:
            d, _ = cKDTree(mine).query(mine, k=2)
            gaps.append(d[:, 1])
    if not gaps:
        d, _ = cKDTree(xy).query(xy, k=2)
        gaps.append(d[:, 1])
    return float(np.median(np.concatenate(gaps)))
