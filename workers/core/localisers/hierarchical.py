"""The ``hierarchical`` localiser of Li et al.: a coarse hue stage, then SIFT decides.

The coarse stage ranks every map image by the Euclidean distance of its HSI hue histogram
(Li eq. 4) to the frame's and keeps the ``k`` closest; the fine stage matches the frame's
SIFT features against each candidate (Lowe's ratio test, optionally verified by RANSAC) and
the candidate with the largest share of matched keypoints gives the position. Like
``retrieval`` it keeps no belief between frames; the reported uncertainty is the
match-weighted spread of the best candidates.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass

import numpy as np

from ..estimate import Estimate, Status
from ..mapdata import MapData
from ..measures import distances
from ..pf.config import VERIFICATIONS
from ..query import QueryFrame
from ..sift import RATIO
from .base import SPREAD_CANDIDATES, StatelessLocaliser, candidate_spread, check_param_keys
from .scoring import sift_similarity


@dataclass(frozen=True)
class HierarchicalConfig:
    """Parameters of the ``hierarchical`` localiser.

    Attributes
    ----------
    k : int
        Candidates kept by the coarse hue stage.
    sift_ratio : float
        Lowe's ratio-test threshold of the fine stage (Lowe 2004's 0.8).
    sift_verify : {"none", "homography", "fundamental"}
        Geometric verification of the matches.
    """

    k: int = 5
    sift_ratio: float = RATIO
    sift_verify: str = "none"

    def __post_init__(self) -> None:
        k = self.k
        if not isinstance(k, int) or isinstance(k, bool) or not 1 <= k <= 1000:
            raise ValueError(f"k must be an integer in 1..1000, got {k!r}")
        r = self.sift_ratio
        if not isinstance(r, int | float) or not 0 < r < 1:
            raise ValueError(f"sift_ratio must be in (0, 1), got {r!r}")
        if self.sift_verify not in VERIFICATIONS:
            raise ValueError(f"sift_verify must be one of {', '.join(VERIFICATIONS)}")

    @classmethod
    def from_params(cls, params: dict) -> HierarchicalConfig:
        check_param_keys("hierarchical", params, cls)
        return cls(**params)

    def to_params(self) -> dict:
        return asdict(self)


class HierarchicalLocaliser(StatelessLocaliser):
    """Li et al.: hue-histogram candidates (Euclidean distance), then SIFT decides.

    Parameters
    ----------
    map_data : MapData
        Must hold ``hue_hist`` features.
    params : dict
        :class:`HierarchicalConfig` fields.
    seed : int
    """

    mode = "hierarchical"

    def __init__(self, map_data: MapData, params: dict, seed: int) -> None:
        super().__init__(map_data, params, seed)
        if "hue_hist" not in map_data.global_features:
            raise ValueError("map has no hue_hist features")
        self.config = HierarchicalConfig.from_params(params)
        self.k = min(self.config.k, len(map_data))

    def _step(self, query: QueryFrame, t0: float) -> Estimate:
        q, hue_ms = query.global_features(("hue_hist",))
        q_sift, sift_ms = query.sift()
        t1 = time.perf_counter()
        d = distances("l2", q["hue_hist"], self.map.global_features["hue_hist"])
        cand = np.argsort(d, kind="stable")[: self.k]
        s = sift_similarity(q_sift, self.map, cand, ratio=self.config.sift_ratio,
                            verify=self.config.sift_verify)
        order = np.argsort(-s, kind="stable")
        cand, s = cand[order], s[order]
        xy = np.asarray(self.map.positions)
        cov = candidate_spread(xy, cand[:SPREAD_CANDIDATES], s[:SPREAD_CANDIDATES])
        ms = hue_ms + sift_ms + (time.perf_counter() - t1) * 1e3
        return self._estimate(xy[cand[0]], cov, feature="sift", next_feature="sift",
                              measurement="sift", n_particles=0, status=Status.TRACKING,
                              processing_ms=ms, best_image=int(cand[0]))
