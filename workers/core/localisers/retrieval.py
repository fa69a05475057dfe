"""The ``retrieval`` localiser (Erhard et al., Flyphone 4.2): the most similar map image.

It keeps no belief between frames: each frame's position is the position of the map image
it resembles most under one global feature and measure. The reported uncertainty is the
similarity-weighted spread of the best few candidates (:func:`.base.candidate_spread`), so a
frame that looks like several distant places says so.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass

import numpy as np

from ..estimate import Estimate, Status
from ..features import ALL_FEATURE_NAMES
from ..mapdata import MapData
from ..measures import MEASURES
from ..query import QueryFrame
from .base import SPREAD_CANDIDATES, StatelessLocaliser, candidate_spread, check_param_keys
from .scoring import check_map_features, every_image_similarity


@dataclass(frozen=True)
class RetrievalConfig:
    """Parameters of the ``retrieval`` localiser.

    Attributes
    ----------
    feature : str
        Global feature (a name in :data:`workers.core.features.ALL_FEATURE_NAMES`): a
        histogram feature or a place descriptor (``vlad_orb``, ``bow_orb``, ...).
    measure : str
        Measure (a name in :data:`workers.core.measures.MEASURES`) for histogram features;
        Bradley's is Flyphone's best pairing for WGOH (Fig. 7). Place descriptors are
        compared by their cosine.
    """

    feature: str = "wgoh"
    measure: str = "bradley"

    def __post_init__(self) -> None:
        if self.feature not in ALL_FEATURE_NAMES:
            raise ValueError(f"unknown feature {self.feature!r}; "
                             f"valid: {', '.join(ALL_FEATURE_NAMES)}")
        if self.measure not in MEASURES:
            raise ValueError(f"unknown measure {self.measure!r}; valid: {', '.join(MEASURES)}")

    @classmethod
    def from_params(cls, params: dict) -> RetrievalConfig:
        check_param_keys("retrieval", params, cls)
        return cls(**params)

    def to_params(self) -> dict:
        return asdict(self)


class RetrievalLocaliser(StatelessLocaliser):
    """Flyphone 4.2: the nearest map image under one global feature and measure.

    Parameters
    ----------
    map_data : MapData
    params : dict
        :class:`RetrievalConfig` fields.
    seed : int
    """

    mode = "retrieval"

    def __init__(self, map_data: MapData, params: dict, seed: int) -> None:
        super().__init__(map_data, params, seed)
        self.config = RetrievalConfig.from_params(params)
        self.feature = self.config.feature
        check_map_features(map_data, (self.feature,))

    def _step(self, query: QueryFrame, t0: float) -> Estimate:
        q, feat_ms = query.global_features((self.feature,), self.map.vocabularies)
        t1 = time.perf_counter()
        s = every_image_similarity(q, self.map, features=(self.feature,),
                                   measure=self.config.measure)
        top = np.argsort(-s, kind="stable")[:SPREAD_CANDIDATES]
        xy = np.asarray(self.map.positions)
        cov = candidate_spread(xy, top, s[top] - s[top].min() + 1e-12)
        ms = feat_ms + (time.perf_counter() - t1) * 1e3
        return self._estimate(xy[top[0]], cov, feature=self.feature, next_feature=self.feature,
                              measurement="global", n_particles=0, status=Status.TRACKING,
                              processing_ms=ms, best_image=int(top[0]))
