"""The particle-filter localisers: ``hybrid`` (Weiss IV-B), ``global`` and ``sift``.

Per frame: build the measurement of the feature type the switching rule chose
(:class:`~workers.core.pf.measurement.ImageSimilarity` over global features or SIFT), run one
filter step, gather the evidence the rule needs and let :func:`~workers.core.pf.switching.decide`
choose the next step's feature type. ``global`` and ``sift`` pin the feature type.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from ..estimate import Estimate, Status
from ..features import DESCRIPTORS
from ..mapdata import MapData
from ..pf import switching
from ..pf.config import config_from_params
from ..pf.filter import ParticleFilter, StepResult
from ..pf.measurement import ImageSimilarity, Likelihood, Position
from ..pf.motion import MotionModel
from ..pf.switching import GLOBAL, SIFT, StepEvidence, SwitchState
from ..query import QueryFrame
from ..sift import SiftFeatures
from .base import Localiser
from .refine import Refinement, refine_sift
from .scoring import check_map_features, global_similarity, sift_similarity

MIN_REDUCED_KEYPOINTS = 20
"""Below this many keypoints surviving the match with the previous frame, the frame is kept
whole: the platform moved too far for the frames to overlap usefully."""

PINNED = {"global": GLOBAL, "sift": SIFT}
"""Feature type of the single-feature filter modes."""


class FilterLocaliser(Localiser):
    """Particle filter with hybrid switching, or pinned to one feature type.

    Parameters
    ----------
    map_data : MapData
    params : dict
        Flat :class:`~workers.core.pf.config.FilterConfig` parameters and ``config`` (a
        named base).
    seed : int
    mode : {"hybrid", "global", "sift"}
    """

    def __init__(self, map_data: MapData, params: dict, seed: int, mode: str) -> None:
        super().__init__(map_data, params, seed)
        self.mode = mode
        self.config = cfg = config_from_params(params)
        if mode != "sift" or cfg.sift.candidates:
            # only the place descriptors: maps have always carried every histogram feature
            check_map_features(map_data, tuple(n for n in cfg.measurement.global_features
                                               if n in DESCRIPTORS))
        speed = map_data.typical_speed() if cfg.motion.speed == "auto" else cfg.motion.speed
        self.motion = MotionModel(sigma_floor=cfg.motion.sigma, speed=speed,
                                  pull=cfg.motion.pull, velocity=cfg.motion.velocity,
                                  nominal_dt=map_data.typical_interval() or 1.0)
        # A particle between two map images is at most half the spacing from one; the
        # factor should fall off over about that, not over the motion noise.
        scale = cfg.measurement.distance_scale or max(0.7 * map_data.median_spacing(),
                                                      0.5 * cfg.motion.sigma)
        self.pf = ParticleFilter(np.asarray(map_data.positions), map_data.tree, cfg,
                                 self.motion, scale, self.rng)
        self.pinned = PINNED.get(mode)
        self.switch = SwitchState(switching.start(self.pinned))
        self.thresholds = switching.thresholds(cfg.switching, self.motion.sigma(None))
        # Agreement within one map spacing (or d_global, if larger): the scaled thresholds
        # grow with the motion noise and would let chance agree.
        self._agree_radius = max(cfg.switching.d_global, map_data.median_spacing())
        self.prev_sift: SiftFeatures | None = None
        self.prev_key = None
        self.last_time: float | None = None

    def _step(self, query: QueryFrame, t0: float) -> Estimate:
        dt = None
        if query.captured_at is not None and self.last_time is not None:
            dt = query.captured_at - self.last_time
        used = self.switch.next
        measurement, feat_ms = self._measurement(query, used)
        fixes: list[Refinement] = []
        refine = self._refiner(query, fixes) if used == SIFT else None
        t_filter = time.perf_counter()
        result = self.pf.step([measurement], dt, refine=refine)
        evidence = StepEvidence(used, result.stats.spread, self._global_gap(used, result))
        filter_ms = (time.perf_counter() - t_filter) * 1e3
        if switching.judges_trust(self.config.switching, used, self.pinned):
            t_judge = time.perf_counter()
            trust_gap, extract_ms = self._trust_gap(query, result.stats.mean)
            evidence = replace(evidence, trust_gap=trust_gap)
            # the check's own time, plus extraction done earlier and cached on the frame
            judge_ms = (time.perf_counter() - t_judge) * 1e3
            filter_ms += judge_ms
            feat_ms += max(extract_ms - judge_ms, 0.0)
        self.switch = switching.decide(self.config.switching, self.switch, evidence,
                                       thresholds=self.thresholds,
                                       agree_radius=self._agree_radius, pinned=self.pinned)
        if used == SIFT:
            self.prev_sift, self.prev_key = query.sift()[0], query.key
        else:
            self.prev_sift, self.prev_key = None, None
        if query.captured_at is not None:
            self.last_time = query.captured_at
        fix = fixes[0] if fixes else None
        heading = None if fix is None or fix.heading_deg is None \
            else (fix.heading_deg, fix.heading_sigma_deg)
        return self._result(result, used, feat_ms + filter_ms, heading)

    def _refiner(self, query: QueryFrame, fixes: list[Refinement]):
        """The step's metric refinement (None when off): it solves the frame's pose against
        the map images the SIFT measurement scored best and records what it found."""
        cfg = self.config.refine
        if not cfg.enabled:
            return None

        def refine(likelihoods: tuple[Likelihood, ...]) -> Position | None:
            images = likelihoods[0]
            order = np.argsort(-images.similarities, kind="stable")
            fix = refine_sift(query.sift()[0], self.map, images.scored[order],
                              images.similarities[order], frame_shape=query.frame.grey.shape)
            if fix is None:
                return None
            fixes.append(fix)
            return Position(fix.kind, fix.xy, fix.sigma, cfg.outlier)

        return refine

    def _result(self, result: StepResult, used: str, processing_ms: float,
                heading: tuple[float, float] | None = None) -> Estimate:
        stats = result.stats
        if stats.spread < self.thresholds[1]:
            status = Status.TRACKING
        else:
            status = Status.LOST if self.stats.get("ever_tracked") else Status.INITIALISING
        if status is Status.TRACKING:
            self.stats["ever_tracked"] = 1
        images = result.likelihoods[0]
        best = int(images.scored[np.argmax(images.similarities)]) if len(images.scored) else -1
        return self._estimate(stats.mean, stats.cov, feature=used, next_feature=self.switch.next,
                              measurement="+".join(result.kinds), n_particles=len(self.pf.w),
                              status=status, processing_ms=processing_ms, best_image=best,
                              heading=heading)

    # -- measurements ----------------------------------------------------------------------

    def _measurement(self, query: QueryFrame, kind: str) -> tuple[ImageSimilarity, float]:
        """The frame's image-similarity measurement under ``kind``, and the extraction ms."""
        cfg = self.config
        m = cfg.measurement
        if kind == GLOBAL:
            q, feat_ms = query.global_features(m.global_features, self.map.vocabularies)

            def similarity(idx: np.ndarray) -> np.ndarray:
                return global_similarity(q, self.map, idx, features=m.global_features,
                                         measure=m.global_measure)

            every = cfg.reset.replacement == "retrieval" or cfg.switching.global_check > 0
            return ImageSimilarity(GLOBAL, similarity, m.global_power, self.pf.distance_scale,
                                   every_image=every), feat_ms
        if cfg.sift.reduce in ("both", "query"):
            q_sift, feat_ms = query.reduced_sift(self.prev_sift, self.prev_key,
                                                 ratio=cfg.sift.ratio,
                                                 min_keep=MIN_REDUCED_KEYPOINTS)
        else:
            q_sift, feat_ms = query.sift()
        reduced_map = cfg.sift.reduce in ("both", "map")
        candidates = None
        if cfg.sift.candidates:
            # The cheap global features shortlist places for SIFT to verify.
            g, g_ms = self._global_scores(query)
            feat_ms += g_ms
            candidates = np.argsort(-g, kind="stable")[: cfg.sift.candidates]

        known: dict[int, float] = {}

        def similarity(idx: np.ndarray) -> np.ndarray:
            # Memoised: a refined step weighs the particles twice (before and after some
            # are drawn around the solved position), and SIFT matching is the step's cost.
            new = np.array([i for i in np.asarray(idx).tolist() if i not in known], np.int64)
            if len(new):
                sims = sift_similarity(q_sift, self.map, new, ratio=cfg.sift.ratio,
                                       verify=cfg.sift.verify, reduced=reduced_map)
                known.update(zip(new.tolist(), sims.tolist(), strict=True))
            return np.array([known[i] for i in np.asarray(idx).tolist()], np.float64)

        return ImageSimilarity(SIFT, similarity, m.sift_power, self.pf.distance_scale,
                               candidates=candidates), feat_ms

    def _global_scores(self, query: QueryFrame) -> tuple[np.ndarray, float]:
        """Global similarity of the frame with every map image, and the extraction ms.

        Called on SIFT steps only (candidates, trust check): the frame's SIFT is at hand.
        """
        m = self.config.measurement
        q, ms = query.global_features(m.global_features, self.map.vocabularies, sift_paid=True)
        return global_similarity(q, self.map, np.arange(len(self.map)),
                                 features=m.global_features, measure=m.global_measure), ms

    # -- evidence for the switching rule ---------------------------------------------------

    def _global_gap(self, used: str, result: StepResult) -> float | None:
        if not switching.checks_global(self.config.switching, used, self.pinned):
            return None
        images = result.likelihoods[0]
        return switching.gap_to_best(self.pf.map_xy[images.scored], images.similarities,
                                     self.config.switching.global_check, result.stats.mean)

    def _trust_gap(self, query: QueryFrame, estimate: np.ndarray) -> tuple[float, float]:
        """How far the global features' best images lie from the SIFT estimate, and the
        milliseconds spent extracting global features for it."""
        g, ms = self._global_scores(query)
        gap = switching.gap_to_best(np.asarray(self.map.positions), g,
                                    self.config.switching.global_trust, estimate)
        return gap, ms

    # -- state ---------------------------------------------------------------------------

    def _state(self) -> tuple[dict[str, np.ndarray], dict]:
        arrays, meta = self.pf.state()
        arrays = {f"pf_{k}": v for k, v in arrays.items()}
        if self.prev_sift is not None:
            arrays["prev_kp"] = self.prev_sift.keypoints
            arrays["prev_desc"] = self.prev_sift.descriptors
        # the next feature type sits beside the particles, where checkpoints have kept it
        meta["mode"] = self.switch.next
        return arrays, {"pf": meta, "last_time": self.last_time, "trust": self.switch.trust}

    def _load(self, arrays: dict[str, np.ndarray], meta: dict) -> None:
        self.pf.load({k[3:]: v for k, v in arrays.items() if k.startswith("pf_")}, meta["pf"])
        self.switch = SwitchState(meta["pf"]["mode"], float(meta["trust"]))
        self.last_time = meta["last_time"]
        if "prev_desc" in arrays:
            self.prev_sift = SiftFeatures(arrays["prev_kp"], arrays["prev_desc"])
        else:
            self.prev_sift = None
        self.prev_key = None

    def reset(self) -> None:
        self.pf.initialise()
        self.switch = SwitchState(switching.start(self.pinned))
        self.prev_sift, self.prev_key, self.last_time = None, None, None
        self.stats.pop("ever_tracked", None)

    def set_initial_pose(self, x: float, y: float, sigma: float = 5.0) -> None:
        self.pf.set_pose(x, y, sigma)
        self.switch = replace(self.switch, next=switching.start(self.pinned))
        self.prev_sift, self.prev_key = None, None
