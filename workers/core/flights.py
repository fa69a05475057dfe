"""A map's flights: its images grouped by the flight (or pass) that took them.

A map may hold several flights over the same ground (a survey flown again weeks later, in
other light or season). An image may say which flight it belongs to (a name given with the
upload, or the survey CSV's ``pass`` column); the others are grouped by when they were
taken: a run of captures with no gap longer than :data:`FLIGHT_GAP_S` between consecutive
ones is a flight, and images with neither a name nor a capture time belong to none.
Unnamed flights flown at the same time by several platforms fall into one.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

FLIGHT_GAP_S: float = 30 * 60.0
"""A pause without captures longer than this (s) ends a flight: a battery change takes
minutes, a second survey of the same ground hours or weeks."""


def flight_labels(captured_at, flights=None, gap_s: float = FLIGHT_GAP_S) -> np.ndarray:
    """Each image's flight, numbered 0, 1, ... in time order; -1 for an image with neither
    a flight name nor a capture time.

    Parameters
    ----------
    captured_at : (n,) float array-like
        Capture times (s since the epoch), NaN where unknown.
    flights : (n,) sequence of str or None, optional
        The flight each image was said to belong to, None where not said. Images of one
        name are one flight whatever their times; the others are grouped by time gaps.
    gap_s : float
        The longest pause within one flight of unnamed images.

    Returns
    -------
    (n,) int64 ndarray
        Flights are numbered by their first capture (flights with no timed image after
        the others, by name).
    """
    t = np.asarray(captured_at, np.float64).reshape(-1)
    named = [None] * len(t) if flights is None else list(flights)
    if len(named) != len(t):
        raise ValueError(f"flights must have one entry per image ({len(t)}), got {len(named)}")
    groups: dict[object, list[int]] = {}
    unnamed = np.array([name is None for name in named], bool)
    timed = np.flatnonzero(np.isfinite(t) & unnamed)
    if len(timed):
        order = timed[np.argsort(t[timed], kind="stable")]
        run = np.cumsum(np.concatenate([[0], np.diff(t[order]) > gap_s]))
        for i, r in zip(order.tolist(), run.tolist(), strict=True):
            groups.setdefault(("gap", r), []).append(i)
    for i, name in enumerate(named):
        if name is not None:
            groups.setdefault(("name", str(name)), []).append(i)

    def first(item) -> tuple:
        key, members = item
        start = np.nanmin(t[members]) if np.isfinite(t[members]).any() else np.inf
        return (start, key[0] == "gap", str(key[1]))

    labels = np.full(len(t), -1, np.int64)
    for label, (_, members) in enumerate(sorted(groups.items(), key=first)):
        labels[members] = label
    return labels


def flight_spacing(positions, captured_at=None, flights=None) -> float:
    """A survey's spacing (m): the median distance from each image to the nearest other
    image of its own flight.

    A second flight over the same ground (the same waypoints flown again) puts an image of
    the other flight within metres of each one, or on top of it: the spacing over every
    image would shrink to that, and whatever is sized by it (how far apart tie points are
    matched, how far a particle's likelihood reaches) with it. Flights are as
    :func:`flight_labels` makes them (``flights``: the names given); images of no flight
    count as one; where no flight holds two images, every image is measured against every
    other. Returns 1.0 for fewer than two images.
    """
    xy = np.asarray(positions, np.float64).reshape(-1, 2)
    if len(xy) < 2:
        return 1.0
    if captured_at is None and flights is None:
        labels = np.full(len(xy), -1, np.int64)
    else:
        times = np.full(len(xy), np.nan) if captured_at is None else captured_at
        labels = flight_labels(times, flights)
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
