"""Tie points between map images: which pairs to match, and their verified matches.

A pair's tie points are the SIFT ratio-test matches between two GPS-neighbouring map images
that agree with their two-view geometry, estimated by COLMAP (:func:`pycolmap.estimate_two_view_geometry`):
a fundamental matrix where the scene has depth, a homography where the pair sees a plane
or turns on the spot. Nothing here assumes a ground plane, so nadir, oblique and
street-level maps are matched alike. Pairs are independent and each one's RANSAC is seeded by
its indices alone, so they can be matched anywhere, in any order
(:mod:`workers.core.tiepairs` matches them on the engine's workers); the reconstruction
(:mod:`.sfm`) reads the keypoint indices of every verified match.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

TIE_RANSAC_TRIALS: int = 2000
"""Most RANSAC trials a pair's two-view geometry may take (COLMAP's default is 10,000).

About half the pairs a survey's GPS plans see different ground: 20-60 ratio matches, none
of them agreeing. RANSAC stops early once a model holds most matches, so a pair that
overlaps costs tens of milliseconds, but one that does not runs every trial, for both the
fundamental matrix and the homography: about a second of a two-core machine's CPU, most of
a map's tie-point matching. At 2,000 trials the matching of the first 60 seneca-uav images
(421 pairs) takes 48 s instead of 222 s and lewis-uav's (55 images, 299 pairs) 43 s instead
of 161 s; the pairs that then fail to verify (8 of 222 and 12 of 195) had 15-19 agreeing
matches of 33-70, as many as pairs that never verify reach (up to 14).

Fewer trials lose real pairs: at 500 the seneca-uav map (70 images) keeps 275 of its 286
verified pairs (``bench/bench_tie_ransac.py``), COLMAP places 62 of its images instead of
64, and the hybrid's mean error is 0.1-0.25 m worse with either of two build seeds. Each
pair's trials are capped instead by the inlier ratio it could verify with
(:func:`ransac_floor`)."""


def ransac_floor(n_matches: int, min_inliers: int) -> float:
    """The lowest inlier ratio a pair of ``n_matches`` ratio matches can verify with:
    ``min_inliers`` of them, at least.

    Given to COLMAP's RANSAC as its ``min_inlier_ratio``, it caps the trials at those that
    find a model of that many inliers with the RANSAC's confidence (0.999, three times
    over), estimator by estimator: a pair of 28 matches, about the median of those that do
    not verify in seneca-uav, needs 1,627 trials of the fundamental matrix's 7-point
    samples and 242 of the homography's 4-point ones, not 2,000 of each; one of 40 needs
    1,038 of the homography's. Pairs that would verify come out as without it (every pair
    of the seneca-uav and lewis-uav maps to the last inlier, and one seneca-uav pair more
    verifies) and their two-view geometry takes 20-28 % less time. COLMAP's own floor,
    0.25, stays where it is higher (more than 60 matches)."""
    return min(max(min_inliers / max(n_matches, 1), 0.25), 1.0)


@dataclass(frozen=True)
class PairMatches:
    """Verified tie points between map images ``a`` and ``b``.

    Attributes
    ----------
    a, b : int
        Map images, ``a < b``.
    matches : (n, 2) int64 ndarray
        Rows of (keypoint of ``a``, keypoint of ``b``): indices into each image's tie points.
    config : int
        COLMAP's two-view configuration (:class:`pycolmap.TwoViewGeometryConfiguration`):
        calibrated, uncalibrated, planar, panoramic...
    """

    a: int
    b: int
    matches: np.ndarray
    config: int

    def __len__(self) -> int:
        return len(self.matches)


def candidate_pairs(positions: np.ndarray, *, max_distance: float,
                    neighbours: int) -> list[tuple[int, int]]:
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
               min_inliers: int = 15, seed: int = 0) -> PairMatches | None:
    """Verified tie points between map images ``a`` and ``b``: the ratio-test matches that
    agree with their two-view geometry; None when fewer than ``min_inliers`` agree.

    Keypoints are pixels at the working resolution (first two columns). The geometry is
    estimated uncalibrated: the map camera's focal length is what the reconstruction finds.
    COLMAP's RANSAC is seeded by ``(seed, a, b)`` alone, so a pair gives the same tie points
    whichever process matches it and whatever it matched before.
    """
    from ..sift import ratio_matches

    m = ratio_matches(descriptors_a, descriptors_b, ratio=ratio)
    if len(m) < min_inliers:
        return None
    return verify_matches(a, b, keypoints_a, keypoints_b, m, min_inliers=min_inliers,
                          seed=seed)


def verify_matches(a: int, b: int, keypoints_a: np.ndarray, keypoints_b: np.ndarray,
                   matches: np.ndarray, *, min_inliers: int = 15, seed: int = 0,
                   trials: int = TIE_RANSAC_TRIALS, capped: bool = True,
                   ) -> PairMatches | None:
    """The ``matches`` (rows of keypoint indices into ``a`` and ``b``) that agree with the
    pair's two-view geometry, by COLMAP's RANSAC of at most ``trials`` trials, capped by
    :func:`ransac_floor` where ``capped``; None when fewer than ``min_inliers`` agree.
    :func:`match_pair`'s second half (``bench/bench_tie_ransac.py`` tries other budgets)."""
    import pycolmap

    from .sfm import colmap_camera, to_colmap_pixels

    options = pycolmap.TwoViewGeometryOptions()
    options.min_num_inliers = min_inliers
    options.ransac.max_num_trials = trials
    if capped:
        options.ransac.min_inlier_ratio = ransac_floor(len(matches), min_inliers)
    options.ransac.random_seed = (seed * 1_000_003 + a * 100_003 + b) % 2 ** 31
    # COLMAP's Sampson refinement polishes the pair's fundamental matrix, which nothing here
    # reads (the build keeps the inlier matches and the configuration): with it off they
    # came out the same, every pair, for seneca-uav's 474, lewis-uav's 163 and the service
    # tests' 45, and a pair took 6-9 % less time
    options.use_sampson_refinement = False
    camera = colmap_camera(None)
    geometry = pycolmap.estimate_two_view_geometry(
        camera, to_colmap_pixels(keypoints_a), camera, to_colmap_pixels(keypoints_b),
        np.asarray(matches).astype(np.uint32), options)
    inliers = np.asarray(geometry.inlier_matches, np.int64).reshape(-1, 2)
    if len(inliers) < min_inliers:
        return None
    return PairMatches(a, b, inliers, int(geometry.config))


def match_pairs(keypoints: Sequence[np.ndarray], descriptors: Sequence[np.ndarray],
                planned: Sequence[tuple[int, int]], *, seed: int = 0,
                known: dict[tuple[int, int], PairMatches | None] | None = None,
                **options) -> list[PairMatches]:
    """Verified matches of the ``planned`` pairs of map images (:func:`match_pair`), in
    their order.

    Parameters
    ----------
    keypoints : sequence of (K_i, >=2) float arrays
        Pixel coordinates in the first two columns; read by index, a pair at a time.
    descriptors : sequence of (K_i, D) arrays
        SIFT (float-comparable) descriptors.
    planned : sequence of (a, b)
        The pairs to match (:func:`workers.core.geometry.tie_pairs`).
    known : dict, optional
        Pairs already matched elsewhere with the same ``seed`` (the build matches them in
        parallel), their result None where they did not verify; the others are matched here.
    options
        :func:`match_pair`'s.
    """
    verified = []
    for a, b in planned:
        if known is not None and (a, b) in known:
            p = known[(a, b)]
        else:
            p = match_pair(a, b, keypoints[a], descriptors[a], keypoints[b], descriptors[b],
                           seed=seed, **options)
        if p is not None:
            verified.append(p)
    return verified
