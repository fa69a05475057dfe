"""Single-frame localisers: ``retrieval`` (Flyphone) and ``hierarchical`` (Li et al.).

Neither keeps a belief between frames: each frame's position is the position of the map
image it resembles most. The reported uncertainty is the similarity-weighted spread of the
best few candidates, so a frame that looks like several distant places says so.
"""

from __future__ import annotations

import time

import numpy as np

from ..estimate import Estimate, Status
from ..mapdata import MapData
from ..query import QueryFrame
from ..similarity import distances
from .base import StatelessLocaliser
from .similarity_models import check_map_features, global_similarity, sift_similarity

SPREAD_CANDIDATES = 5


def _spread(map_xy: np.ndarray, idx: np.ndarray, score: np.ndarray) -> np.ndarray:
    """Covariance of the candidate positions weighted by their scores (normalised)."""
    w = np.clip(score, 0.0, None)
    if w.sum() <= 0:
        w = np.ones_like(w)
    w = w / w.sum()
    pts = map_xy[idx]
    d = pts - w @ pts
    return (d * w[:, None]).T @ d


class RetrievalLocaliser(StatelessLocaliser):
    """Flyphone 4.2: the nearest map image under one global feature and measure.

    Parameters (``params``)
    -----------------------
    feature : str, default "wgoh"
        A histogram feature or a place descriptor (``vlad_orb``, ``bow_orb``, ...).
    measure : str, default "bradley" (Flyphone's best pairing for WGOH, Fig. 7)
        For histogram features; place descriptors are compared by their cosine.
    """

    mode = "retrieval"

    def __init__(self, map_data: MapData, params: dict, seed: int) -> None:
        super().__init__(map_data, params, seed)
        self.feature = params["feature"]
        self.measure = params["measure"]
        check_map_features(map_data, (self.feature,))

    def _step(self, query: QueryFrame, t0: float) -> Estimate:
        q, feat_ms = query.global_features((self.feature,), self.map.vocabularies)
        t1 = time.perf_counter()
        s = global_similarity(q, self.map, np.arange(len(self.map)), features=(self.feature,),
                              measure=self.measure)
        top = np.argsort(-s, kind="stable")[:SPREAD_CANDIDATES]
        xy = np.asarray(self.map.positions)
        cov = _spread(xy, top, s[top] - s[top].min() + 1e-12)
        ms = feat_ms + (time.perf_counter() - t1) * 1e3
        return self._estimate(xy[top[0]], cov, feature=self.feature, next_feature=self.feature,
                              n_particles=0, status=Status.TRACKING, processing_ms=ms,
                              best_image=int(top[0]))


class HierarchicalLocaliser(StatelessLocaliser):
    """Li et al.: hue-histogram candidates (Euclidean distance), then SIFT decides.

    Parameters (``params``)
    -----------------------
    k : int, default 5
        Candidates kept by the coarse hue stage.
    sift_ratio : float, default 0.8
    sift_verify : {"none", "homography", "fundamental"}, default "none"
    """

    mode = "hierarchical"

    def __init__(self, map_data: MapData, params: dict, seed: int) -> None:
        super().__init__(map_data, params, seed)
        if "hue_hist" not in map_data.global_features:
            raise ValueError("map has no hue_hist features")
        self.k = min(int(params["k"]), len(map_data))

    def _step(self, query: QueryFrame, t0: float) -> Estimate:
        q, hue_ms = query.global_features(("hue_hist",))
        q_sift, sift_ms = query.sift()
        t1 = time.perf_counter()
        d = distances("l2", q["hue_hist"], self.map.global_features["hue_hist"])
        cand = np.argsort(d, kind="stable")[: self.k]
        s = sift_similarity(q_sift, self.map, cand, ratio=self.params["sift_ratio"],
                            verify=self.params["sift_verify"])
        order = np.argsort(-s, kind="stable")
        cand, s = cand[order], s[order]
        xy = np.asarray(self.map.positions)
        cov = _spread(xy, cand[:SPREAD_CANDIDATES], s[:SPREAD_CANDIDATES])
        ms = hue_ms + sift_ms + (time.perf_counter() - t1) * 1e3
        return self._estimate(xy[cand[0]], cov, feature="sift", next_feature="sift",
                              n_particles=0, status=Status.TRACKING, processing_ms=ms,
                              best_image=int(cand[0]))
