"""Tie points between map images: which pairs to match, and their verified matches.

Two overlapping aerial images of nearly flat ground are related by a homography: a pair's
tie points are the SIFT ratio-test matches that agree with one (RANSAC), and the bundle
adjustment (:mod:`.reconstruct`) keeps a few dozen of them a pair. Pairs are independent and
each one's RANSAC is seeded by its indices alone, so they can be matched anywhere, in any
order (:mod:`workers.core.tiepairs` matches them on the engine's workers).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree


@dataclass(frozen=True)
class PairMatches:
    """Verified tie points between map images ``a`` and ``b`` (pixels in each)."""

    a: int
    b: int
    pa: np.ndarray  # (n, 2) float64
    pb: np.ndarray  # (n, 2) float64
    homography: np.ndarray  # (3, 3), pixels of a -> pixels of b


def candidate_pairs(positions: np.ndarray, *, max_distance: float,
                    neighbours: int = 8) -> list[tuple[int, int]]:
    """Pairs ``(a, b)``, ``a < b``, of map images worth matching, ascending: each image with
    those of its ``neighbours`` GPS-nearest that lie closer than ``max_distance`` (m)."""
    n = len(positions)
    if n < 2:
        return []
    dist, idx = cKDTree(positions).query(positions, k=min(neighbours + 1, n))
    pairs = set()
    for i in range(n):
        for d, j in zip(np.atleast_1d(dist[i])[1:], np.atleast_1d(idx[i])[1:], strict=True):
            if d <= max_distance and j != i:
                pairs.add((min(i, int(j)), max(i, int(j))))
    return sorted(pairs)


def match_pair(a: int, b: int, keypoints_a: np.ndarray, descriptors_a: np.ndarray,
               keypoints_b: np.ndarray, descriptors_b: np.ndarray, *, ratio: float = 0.8,
               min_inliers: int = 10, ransac_px: float = 3.0,
               seed: int = 0) -> PairMatches | None:
    """Verified tie points between map images ``a`` and ``b``: the ratio-test matches that
    agree with one RANSAC homography, all of them (:func:`keep_some` keeps a few); None when
    fewer than ``min_inliers`` agree.

    OpenCV's RANSAC is seeded by ``(seed, a, b)`` alone, so a pair gives the same tie points
    whichever process matches it and whatever it matched before.
    """
    from ..sift import ratio_matches

    m = ratio_matches(descriptors_a, descriptors_b, ratio=ratio)
    if len(m) < min_inliers:
        return None
    pa = np.asarray(keypoints_a[m[:, 0], :2], np.float64)
    pb = np.asarray(keypoints_b[m[:, 1], :2], np.float64)
    # OpenCV's RANSAC draws from a per-thread generator whose state depends on what the
    # process did before: seed it per pair
    cv2.setRNGSeed((seed * 1_000_003 + a * 100_003 + b) % 2 ** 31)
    H, mask = cv2.findHomography(pa, pb, cv2.RANSAC, ransac_px)
    if H is None:
        return None
    sel = np.flatnonzero(mask.ravel())
    if len(sel) < min_inliers:
        return None
    return PairMatches(a, b, pa[sel], pb[sel], H)


def keep_some(pairs: list[PairMatches], rng: np.random.Generator,
              max_per_pair: int = 30) -> list[PairMatches]:
    """Each pair with at most ``max_per_pair`` of its tie points, drawn at random in the
    order of ``pairs`` (those with fewer keep them all): the bundle adjustment's cost grows
    with the tie points, its accuracy hardly beyond a few dozen a pair."""
    out = []
    for p in pairs:
        if len(p.pa) > max_per_pair:
            keep = np.sort(rng.choice(len(p.pa), size=max_per_pair, replace=False))
            p = PairMatches(p.a, p.b, p.pa[keep], p.pb[keep], p.homography)
        out.append(p)
    return out


def match_pairs(keypoints: Sequence[np.ndarray], descriptors: Sequence[np.ndarray],
                positions: np.ndarray, *, max_distance: float, neighbours: int = 8,
                max_per_pair: int = 30, seed: int = 0,
                known: dict[tuple[int, int], PairMatches | None] | None = None,
                **options) -> list[PairMatches]:
    """Verified matches between each map image and its GPS neighbours
    (:func:`candidate_pairs`, :func:`match_pair`), at most ``max_per_pair`` tie points each
    (:func:`keep_some`, drawn by a generator seeded with ``seed``).

    Parameters
    ----------
    keypoints : sequence of (K_i, >=2) float arrays
        Pixel coordinates in the first two columns; read by index, a pair at a time.
    descriptors : sequence of (K_i, D) arrays
        SIFT (float-comparable) descriptors.
    positions : (N, 2) float ndarray
        GPS east/north of the images.
    max_distance : float
        Only pairs closer than this (m) are tried: further apart the footprints cannot
        overlap.
    known : dict, optional
        Pairs already matched elsewhere with the same ``seed`` (the build matches them in
        parallel), their result None where they did not verify; the others are matched here.
    options
        :func:`match_pair`'s.
    """
    verified = []
    for a, b in candidate_pairs(positions, max_distance=max_distance, neighbours=neighbours):
        if known is not None and (a, b) in known:
            p = known[(a, b)]
        else:
            p = match_pair(a, b, keypoints[a], descriptors[a], keypoints[b], descriptors[b],
                           seed=seed, **options)
        if p is not None:
            verified.append(p)
    return keep_some(verified, np.random.default_rng(seed), max_per_pair)
