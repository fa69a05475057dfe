"""The particle-filter localisers: ``hybrid`` (Weiss IV-B), ``global`` and ``sift``."""

from __future__ import annotations

import time

import numpy as np

from ..estimate import Estimate, Status
from ..features import DESCRIPTORS
from ..mapdata import MapData
from ..pf.config import config_from_params
from ..pf.filter import GLOBAL, SIFT, ParticleFilter
from ..pf.motion import MotionModel
from ..query import QueryFrame
from ..sift import SiftFeatures
from .base import Localiser
from .similarity_models import check_map_features, global_similarity, sift_similarity

TRUST_RATE = 0.3
"""Weight of the newest SIFT step in the running agreement of global features with SIFT."""



MIN_REDUCED_KEYPOINTS = 20
"""Below this many keypoints surviving the match with the previous frame, the frame is kept
whole: the platform moved too far for the frames to overlap usefully."""


class FilterLocaliser(Localiser):
    """Particle filter with hybrid switching, or pinned to one feature type.

    Parameters
    ----------
    map_data : MapData
    params : dict
        :class:`~workers.core.pf.config.FilterConfig` fields and ``config`` (a named base).
    seed : int
    mode : {"hybrid", "global", "sift"}
    """

    def __init__(self, map_data: MapData, params: dict, seed: int, mode: str) -> None:
        super().__init__(map_data, params, seed)
        self.mode = mode
        self.config = cfg = config_from_params(params)
        if mode != "sift" or cfg.sift_candidates:
            # only the place descriptors: maps have always carried every histogram feature
            check_map_features(map_data, tuple(n for n in cfg.global_features
                                               if n in DESCRIPTORS))
        speed = map_data.typical_speed() if cfg.speed == "auto" else cfg.speed
        self.motion = MotionModel(sigma_floor=cfg.motion_sigma, speed=speed, pull=cfg.pull,
                                  velocity=cfg.velocity,
                                  nominal_dt=map_data.typical_interval() or 1.0)
        # A particle between two map images is at most half the spacing from one; the
        # factor should fall off over about that, not over the motion noise.
        scale = cfg.distance_scale or max(0.7 * map_data.median_spacing(),
                                          0.5 * cfg.motion_sigma)
        self.pf = ParticleFilter(np.asarray(map_data.positions), map_data.tree, cfg,
                                 self.motion, scale, self.rng)
        self._fixed = {"global": GLOBAL, "sift": SIFT}.get(mode)
        self._pin()
        self.prev_sift: SiftFeatures | None = None
        self.prev_key = None
        self.last_time: float | None = None
        self.trust = 0.0
        self._agree_radius = max(cfg.d_global, map_data.median_spacing())

    def _pin(self) -> None:
        if self._fixed is not None:
            self.pf.mode = self._fixed

    def _step(self, query: QueryFrame, t0: float) -> Estimate:
        cfg = self.config
        dt = None
        if query.captured_at is not None and self.last_time is not None:
            dt = query.captured_at - self.last_time
        kind = self.pf.mode
        candidates = None
        if kind == GLOBAL:
            q, feat_ms = query.global_features(cfg.global_features, self.map.vocabularies)

            def similarity(idx: np.ndarray) -> np.ndarray:
                return global_similarity(q, self.map, idx, features=cfg.global_features,
                                         measure=cfg.global_measure)
        else:
            if cfg.sift_reduce in ("both", "query"):
                q_sift, feat_ms = query.reduced_sift(self.prev_sift, self.prev_key,
                                                     ratio=cfg.sift_ratio,
                                                     min_keep=MIN_REDUCED_KEYPOINTS)
            else:
                q_sift, feat_ms = query.sift()
            reduced_map = cfg.sift_reduce in ("both", "map")
            if cfg.sift_candidates:
                # The cheap global features shortlist places for SIFT to verify.
                qg, g_ms = query.global_features(cfg.global_features, self.map.vocabularies,
                                                 sift_paid=True)
                feat_ms += g_ms
                every_image = np.arange(len(self.map))
                g = global_similarity(qg, self.map, every_image, features=cfg.global_features,
                                      measure=cfg.global_measure)
                candidates = np.argsort(-g, kind="stable")[: cfg.sift_candidates]

            def similarity(idx: np.ndarray) -> np.ndarray:
                return sift_similarity(q_sift, self.map, idx, ratio=cfg.sift_ratio,
                                       verify=cfg.sift_verify, reduced=reduced_map)
        t_filter = time.perf_counter()
        every = kind == GLOBAL and (cfg.replacement == "retrieval" or cfg.global_check > 0)
        stats, used, scored, sims = self.pf.step(similarity, dt, all_similarities=every,
                                                 candidates=candidates)
        self._pin()
        filter_ms = (time.perf_counter() - t_filter) * 1e3
        if self.mode == "hybrid" and cfg.global_trust:
            t_judge = time.perf_counter()
            extract_ms = self._judge_global(query, used, stats.mean)
            # the check's own time, plus extraction done earlier and cached on the frame
            judge_ms = (time.perf_counter() - t_judge) * 1e3
            filter_ms += judge_ms
            feat_ms += max(extract_ms - judge_ms, 0.0)
        if used == SIFT:
            self.prev_sift, self.prev_key = query.sift()[0], query.key
        else:
            self.prev_sift, self.prev_key = None, None
        if query.captured_at is not None:
            self.last_time = query.captured_at
        _, d_sift = self.pf.thresholds()
        spread = max(stats.sigma_x, stats.sigma_y)
        if spread < d_sift:
            status = Status.TRACKING
        else:
            status = Status.LOST if self.stats.get("ever_tracked") else Status.INITIALISING
        if status is Status.TRACKING:
            self.stats["ever_tracked"] = 1
        best = int(scored[np.argmax(sims)]) if len(scored) else -1
        return self._estimate(stats.mean, stats.cov, feature=used, next_feature=self.pf.mode,
                              n_particles=len(self.pf.w), status=status,
                              processing_ms=feat_ms + filter_ms, best_image=best)

    def _judge_global(self, query: QueryFrame, used: str, estimate: np.ndarray) -> float:
        """Update the trust in global features on SIFT steps; veto global while it is low.

        Returns the milliseconds spent extracting global features for the check.
        """
        cfg = self.config
        ms = 0.0
        if used == SIFT:
            qg, ms = query.global_features(cfg.global_features, self.map.vocabularies,
                                           sift_paid=True)
            g = global_similarity(qg, self.map, np.arange(len(self.map)),
                                  features=cfg.global_features, measure=cfg.global_measure)
            top = np.argsort(-g, kind="stable")[: cfg.global_trust]
            gap = np.min(np.linalg.norm(np.asarray(self.map.positions)[top] - estimate, axis=1))
            # Agreement within one map spacing (or d_global, if larger): the scaled
            # thresholds grow with the motion noise and would let chance agree.
            agree = float(gap <= self._agree_radius)
            self.trust = (1.0 - TRUST_RATE) * self.trust + TRUST_RATE * agree
        if self.trust < cfg.global_trust_level:
            self.pf.mode = SIFT
        return ms

    # -- state ---------------------------------------------------------------------------

    def _state(self) -> tuple[dict[str, np.ndarray], dict]:
        arrays, meta = self.pf.state()
        arrays = {f"pf_{k}": v for k, v in arrays.items()}
        if self.prev_sift is not None:
            arrays["prev_kp"] = self.prev_sift.keypoints
            arrays["prev_desc"] = self.prev_sift.descriptors
        return arrays, {"pf": meta, "last_time": self.last_time, "trust": self.trust}

    def _load(self, arrays: dict[str, np.ndarray], meta: dict) -> None:
        self.pf.load({k[3:]: v for k, v in arrays.items() if k.startswith("pf_")}, meta["pf"])
        self.last_time = meta["last_time"]
        self.trust = float(meta["trust"])
        if "prev_desc" in arrays:
            self.prev_sift = SiftFeatures(arrays["prev_kp"], arrays["prev_desc"])
        else:
            self.prev_sift = None
        self.prev_key = None

    def reset(self) -> None:
        self.pf.initialise()
        self._pin()
        self.prev_sift, self.prev_key, self.last_time = None, None, None
        self.trust = 0.0
        self.stats.pop("ever_tracked", None)

    def set_initial_pose(self, x: float, y: float, sigma: float = 5.0) -> None:
        self.pf.set_pose(x, y, sigma)
        self._pin()
        self.prev_sift, self.prev_key = None, None
