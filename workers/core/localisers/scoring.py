"""Similarity of a query frame with map images, by global features or by SIFT."""

from __future__ import annotations

import cv2
import numpy as np

from ..features import DESCRIPTORS
from ..features.orb import OrbFeatures
from ..mapdata import MapData
from ..measures import descriptor_similarities, similarities
from ..sift import SiftFeatures, ratio_matches

_MIN_VERIFY = {"homography": 4, "fundamental": 8}
RANSAC_PX = 4.0
"""RANSAC inlier threshold in pixels at the working resolution."""


def check_map_features(map_data: MapData, features: tuple[str, ...]) -> None:
    """ValueError unless the map holds every named global feature (and its vocabulary)."""
    for name in features:
        if name not in map_data.global_features or (
                name in DESCRIPTORS and name not in map_data.vocabularies):
            raise ValueError(f"map has no {name!r} features; a build of the map adds them")


def global_similarity(query: dict[str, np.ndarray], map_data: MapData, idx: np.ndarray, *,
                      features: tuple[str, ...], measure: str) -> np.ndarray:
    """Product over ``features`` of the per-feature similarities (Weiss II-C).

    With ``features = ("wgoh", "wgii")`` and ``measure = "weiss"`` this is
    s_WGOH x s_WGII with the normalised intersection of Weiss eq. 1. ``measure`` applies to
    the histogram features; place descriptors are always compared by their cosine
    (:func:`~workers.core.measures.descriptor_similarities`).

    Returns
    -------
    (k,) float64 ndarray in [0, 1]
    """
    s = np.ones(len(idx))
    for name in features:
        if name in DESCRIPTORS:
            s *= descriptor_similarities(query[name], map_data.global_features[name], idx)
        else:
            s *= similarities(measure, query[name], map_data.global_features[name][idx])
    return s


def every_image_similarity(query: dict[str, np.ndarray], map_data: MapData, *,
                           features: tuple[str, ...], measure: str) -> np.ndarray:
    """:func:`global_similarity` of the frame with every map image, (N,) float64.

    On a large map only the shortlist its codes pick is scored (:meth:`MapData.shortlist`);
    the other images stay at zero, below any image worth ranking.
    """
    shortlist = map_data.shortlist(query, features)
    if shortlist is None:
        return global_similarity(query, map_data, np.arange(len(map_data)),
                                 features=features, measure=measure)
    scores = np.zeros(len(map_data))
    scores[shortlist] = global_similarity(query, map_data, shortlist, features=features,
                                          measure=measure)
    return scores


def verified_count(query: SiftFeatures | OrbFeatures, ref: SiftFeatures | OrbFeatures,
                   matches: np.ndarray, method: str) -> int:
    """Number of matches consistent with one geometric model (RANSAC inliers): the
    keypoints' pixels of either local-feature kind."""
    if method == "none" or len(matches) < _MIN_VERIFY[method]:
        return len(matches) if method == "none" else 0
    src = np.ascontiguousarray(query.keypoints[matches[:, 0], :2], dtype=np.float32)
    dst = np.ascontiguousarray(ref.keypoints[matches[:, 1], :2], dtype=np.float32)
    if method == "homography":
        _, mask = cv2.findHomography(src, dst, cv2.RANSAC, RANSAC_PX, maxIters=500,
                                     confidence=0.99)
    else:
        _, mask = cv2.findFundamentalMat(src, dst, cv2.FM_RANSAC, RANSAC_PX, 0.99, 500)
    return 0 if mask is None else int(mask.sum())


def sift_similarity(query: SiftFeatures, map_data: MapData, idx: np.ndarray, *, ratio: float,
                    verify: str, reduced: bool = False) -> np.ndarray:
    """Share of the query's keypoints matched (and verified) in each map image (Weiss III).

    Returns
    -------
    (k,) float64 ndarray in [0, 1]
    """
    out = np.zeros(len(idx))
    n = len(query)
    if n == 0:
        return out
    # Converted once here rather than once per map image inside ratio_matches.
    q_desc = np.asarray(query.descriptors, dtype=np.float32)
    for j, i in enumerate(idx):
        ref = map_data.sift(int(i), reduced=reduced)
        m = ratio_matches(q_desc, ref.descriptors, ratio=ratio)
        out[j] = verified_count(query, ref, m, verify) / n
    return out
