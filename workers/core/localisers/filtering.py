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
from ..metadata import FrameMetadata
from ..pf import switching
from ..pf.config import config_from_params
from ..pf.filter import ParticleFilter, StepResult, cloud_sample, cloud_stats
from ..pf.measurement import ImageSimilarity, Likelihood, Position
from ..pf.motion import MotionModel
from ..pf.switching import GLOBAL, SIFT, StepEvidence, SwitchState
from ..query import QueryFrame
from ..sift import SiftFeatures
from .base import Localiser
from .refine import Refinement, rank_cloud_images, refine_orb, refine_sift
from .scoring import (
    check_map_features,
    every_image_similarity,
    global_similarity,
    sift_similarity,
)
from .sensors import Sensors, heading_agrees, read_sensors

MIN_REDUCED_KEYPOINTS = 20
"""Below this many keypoints surviving the match with the previous frame, the frame is kept
whole: the platform moved too far for the frames to overlap usefully."""

PINNED = {"global": GLOBAL, "sift": SIFT}
"""Feature type of the single-feature filter modes."""

GLOBAL_IMAGES = 3
"""Map images a global step registers against with ORB, one at a time, best first."""

FALLBACK_IMAGES = 5
"""Map images the SIFT fallback of a global step registers against together."""


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
                                 self.motion, scale, self.rng,
                                 spacing=map_data.median_spacing())
        self.pinned = PINNED.get(mode)
        # Where global steps register against the map's geometry, their fixes judge them
        # frame by frame and the running trust in the global features is not needed.
        self.registers_globally = (cfg.refine.enabled and cfg.refine.on_global
                                   and map_data.has_orb and map_data.geometry is not None
                                   and "orb" in map_data.geometry.points)
        if self.registers_globally:
            self.config = cfg = replace(cfg, switching=replace(cfg.switching, global_trust=0))
        self.switch = SwitchState(switching.start(self.pinned))
        self.thresholds = switching.thresholds(cfg.switching, self.motion.sigma(None))
        # Agreement within one map spacing (or d_global, if larger): the scaled thresholds
        # grow with the motion noise and would let chance agree.
        self._agree_radius = max(cfg.switching.d_global, map_data.median_spacing())
        self.prev_sift: SiftFeatures | None = None
        self.prev_key = None
        self.last_time: float | None = None
        # the tracked velocity (drift) and the last step with a metric fix: (time, x, y)
        self.drift: np.ndarray | None = None
        self.anchor: tuple[float, float, float] | None = None
        self.clock = 0.0

    @property
    def escalates(self) -> bool:
        """Whether a global step that finds no fix is taken back for SIFT (``escalate`` on a
        map whose global steps register): trying one costs little, so the switching rule may
        try one after any SIFT step."""
        return self.registers_globally and self.config.switching.escalate

    def _step(self, query: QueryFrame, t0: float) -> Estimate:
        dt = None
        if query.captured_at is not None and self.last_time is not None:
            dt = query.captured_at - self.last_time
        used = self.switch.next
        sensors = self._sensors(query.metadata, dt)
        allowed = self.config.switching.global_misses or 0
        # only where global steps register can one find no fix and be taken back: elsewhere
        # no snapshot of the cloud is needed
        escalate = used == GLOBAL and self.pinned is None and self.escalates
        before = self.pf.snapshot() if escalate else None
        result, fixes, tried, fell_back, ms = self._filter_step(query, used, dt, sensors)
        if fell_back:
            used = SIFT  # the global step registered, or tried to, with SIFT
        if escalate and tried and not fixes and self.switch.misses + 1 > allowed:
            # the cheap step found no fix that agrees with the cloud: this frame gets SIFT
            self.pf.restore(before)
            used = SIFT
            result, fixes, tried, _, more_ms = self._filter_step(query, used, dt, sensors)
            # the SIFT step counts the extraction the fallback already counted
            ms += more_ms - (query.sift()[1] if fell_back else 0.0)
        self._track(dt, result.stats.mean, anchored=bool(fixes))
        evidence = StepEvidence(used, result.spread, self._global_gap(used, result),
                                registered=bool(fixes) if tried else None)
        if switching.judges_trust(self.config.switching, used, self.pinned):
            t_judge = time.perf_counter()
            trust_gap, extract_ms = self._trust_gap(query, result.stats.mean)
            evidence = replace(evidence, trust_gap=trust_gap)
            # the check's own time, plus extraction done earlier and cached on the frame
            judge_ms = (time.perf_counter() - t_judge) * 1e3
            ms += judge_ms + max(extract_ms - judge_ms, 0.0)
        self.switch = switching.decide(self.config.switching, self.switch, evidence,
                                       thresholds=self.thresholds,
                                       agree_radius=self._agree_radius, pinned=self.pinned,
                                       escalates=self.escalates)
        if used == SIFT:
            self.prev_sift, self.prev_key = query.sift()[0], query.key
        else:
            self.prev_sift, self.prev_key = None, None
        if query.captured_at is not None:
            self.last_time = query.captured_at
        fix = fixes[0] if fixes else None
        heading = None if fix is None or fix.heading_deg is None \
            else (fix.heading_deg, fix.heading_sigma_deg)
        return replace(self._result(result, used, ms, heading),
                       metadata_used="+".join(sensors.used), gps_gate=sensors.gps_gate)

    def _filter_step(self, query: QueryFrame, used: str, dt: float | None, sensors: Sensors,
                     ) -> tuple[StepResult, list[Refinement], bool, bool, float]:
        """One filter step with ``used``'s measurement: the result, the metric fixes it
        found, whether it tried to refine, whether a global step fell back on SIFT, and its
        milliseconds (extraction included)."""
        measurement, feat_ms = self._measurement(query, used)
        fixes: list[Refinement] = []
        fallback: list[float] = []
        refine = self._refiner(query, used, fixes, sensors.heading, fallback)
        t_filter = time.perf_counter()
        drift = sensors.velocity if sensors.velocity is not None \
            else (self.drift if self.config.motion.drift else None)
        result = self.pf.step([measurement, *sensors.positions], dt, refine=refine,
                              drift=drift)
        ms = feat_ms + sum(fallback) + (time.perf_counter() - t_filter) * 1e3
        return result, fixes, refine is not None, bool(fallback), ms

    def _sensors(self, metadata: FrameMetadata | None, dt: float | None) -> Sensors:
        """What the frame's metadata adds to the step (:func:`.sensors.read_sensors`),
        judged against the cloud as the last step left it."""
        if metadata is None:
            return Sensors()
        return read_sensors(metadata, self.map.origin, cloud_stats(self.pf.xy, self.pf.w),
                            self.motion.sigma(dt))

    def _refiner(self, query: QueryFrame, used: str, fixes: list[Refinement],
                 compass: tuple[float, float] | None, fallback: list[float]):
        """The step's metric refinement (None when off): it solves the frame's pose against
        the map images the step's measurement ranks best and records what it found.

        SIFT steps register with SIFT against the best SIFT-scored images (or interpolate
        between them on maps without geometry). Global steps, under ``refine_global`` on a
        map with ORB 3-D points, register with ORB against the particles' images the
        global features rank best, or are placed at one of them that has no 3-D points for
        them and that they overlap beyond doubt (:func:`.refine.refine_orb`); such a fix is
        used only where it lies within the gate
        of the predicted cloud and has enough inliers, and the switching rule hears of it.
        Under ``refine_sift_fallback`` (hybrid only) a global step whose ORB finds no fix
        registers with SIFT against the same images; ``fallback`` then receives the SIFT
        extraction's milliseconds where an earlier step had already paid them (a frame
        replayed through several localisers), so that the step's time stays honest.

        A global step's fix weighs the particles alone, without the global similarity: on
        lewis-uav a fix 2.2 m from the truth was reported 26-31 m off while the similarity
        of a look-alike image weighed beside it (mean error 7.7 -> 5.9 m; seneca-uav's
        median 3.2 -> 2.6 m, its mean unchanged until the heaviest cluster is reported).
        """
        cfg = self.config.refine
        use_sift = cfg.sift_fallback and self.pinned is None
        if not cfg.enabled:
            return None
        if used == SIFT:
            def refine(likelihoods: tuple[Likelihood, ...]) -> Position | None:
                images = likelihoods[0]
                order = np.argsort(-images.similarities, kind="stable")
                fix = refine_sift(query.sift()[0], self.map, images.scored[order],
                                  images.similarities[order], frame_shape=query.frame.grey.shape)
                if fix is None or not heading_agrees(fix, compass):
                    return None
                fixes.append(fix)
                return Position(fix.kind, fix.xy, fix.sigma, cfg.outlier)

            return refine
        if not self.registers_globally:
            return None

        def refine_global(likelihoods: tuple[Likelihood, ...]) -> Position | None:
            images = likelihoods[0]
            # the predicted cloud's own images, by their share of the posterior
            order, mass = rank_cloud_images(images.nearest, images.log)
            shape = query.frame.grey.shape
            fix = self._gated(refine_orb(query.orb()[0], self.map, order, mass,
                                         frame_shape=shape, min_inliers=cfg.global_inliers,
                                         max_images=GLOBAL_IMAGES), compass)
            if fix is None and use_sift:
                cached = query.has_sift
                feats, extract_ms = query.sift()
                fallback.append(extract_ms if cached else 0.0)
                fix = self._gated(refine_sift(feats, self.map, order, mass, frame_shape=shape,
                                              max_images=FALLBACK_IMAGES), compass)
            if fix is None:
                return None
            fixes.append(fix)
            # the global features have done their part (which images to register against);
            # a registered pose is far sharper than their likelihood, which would pull the
            # estimate towards the places they confuse
            return Position(fix.kind, fix.xy, fix.sigma, cfg.outlier, alone=True)

        return refine_global

    def _gated(self, fix: Refinement | None,
               compass: tuple[float, float] | None) -> Refinement | None:
        """A global step's fix, or None where it has too few inliers, disagrees with the
        compass, or lies outside the gate of the predicted cloud."""
        if fix is None or fix.inliers < self.config.refine.global_inliers \
                or not heading_agrees(fix, compass):
            return None
        if np.linalg.norm(fix.xy - self.pf.xy.mean(axis=0)) > self._gate_radius():
            return None
        return fix

    def _track(self, dt: float | None, mean: np.ndarray, *, anchored: bool) -> None:
        """Update the tracked velocity from consecutive steps with metric fixes."""
        nominal = self.motion.nominal_dt
        self.clock += dt if dt is not None and np.isfinite(dt) and dt > 0 else nominal
        if not anchored:
            if self.anchor is not None and self.clock - self.anchor[0] > 3.0 * nominal:
                self.drift, self.anchor = None, None  # too long without a fix to trust it
            return
        if self.anchor is not None:
            gap = self.clock - self.anchor[0]
            v = (np.asarray(mean, np.float64) - np.array(self.anchor[1:])) / gap
            limit = 3.0 * (self.motion.speed or self.motion.sigma_floor / nominal)
            if float(np.hypot(*v)) <= limit:
                self.drift = v if self.drift is None else 0.5 * (self.drift + v)
        self.anchor = (self.clock, float(mean[0]), float(mean[1]))

    def _gate_radius(self) -> float:
        """How far from the predicted cloud's mean a global step's fix may lie (m)."""
        spread = float(np.sqrt(np.trace(np.cov(self.pf.xy.T))))
        return max(self._agree_radius, self.config.refine.gate * spread)

    def _result(self, result: StepResult, used: str, processing_ms: float,
                heading: tuple[float, float] | None = None) -> Estimate:
        if result.spread < self.thresholds[1]:
            status = Status.TRACKING
        else:
            status = Status.LOST if self.stats.get("ever_tracked") else Status.INITIALISING
        if status is Status.TRACKING:
            self.stats["ever_tracked"] = 1
        images = result.likelihoods[0]
        best = int(images.scored[np.argmax(images.similarities)]) if len(images.scored) else -1
        reported = result.estimate
        est = self._estimate(reported.mean, reported.cov, feature=used,
                             next_feature=self.switch.next, measurement="+".join(result.kinds),
                             n_particles=len(self.pf.w), status=status,
                             processing_ms=processing_ms, best_image=best, heading=heading)
        # centimetres are plenty for a display and keep the streamed message small
        sample = np.round(cloud_sample(self.pf.xy, self.pf.w), 2)
        return replace(est, cloud=tuple((float(x), float(y)) for x, y in sample))

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
            # on a large map, "every image" is the shortlist its codes pick for this frame
            shortlist = self.map.shortlist(q, m.global_features) if every else None
            return ImageSimilarity(GLOBAL, similarity, m.global_power, self.pf.distance_scale,
                                   every_image=every and shortlist is None,
                                   candidates=shortlist), feat_ms
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
        return every_image_similarity(q, self.map, features=m.global_features,
                                      measure=m.global_measure), ms

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
        return arrays, {"pf": meta, "last_time": self.last_time, "trust": self.switch.trust,
                        "misses": self.switch.misses, "clock": self.clock,
                        "anchor": None if self.anchor is None else list(self.anchor),
                        "drift": None if self.drift is None else self.drift.tolist()}

    def _load(self, arrays: dict[str, np.ndarray], meta: dict) -> None:
        self.pf.load({k[3:]: v for k, v in arrays.items() if k.startswith("pf_")}, meta["pf"])
        self.switch = SwitchState(meta["pf"]["mode"], float(meta["trust"]),
                                  int(meta.get("misses", 0)))
        self.last_time = meta["last_time"]
        self.clock = float(meta.get("clock", 0.0))
        self.anchor = None if meta.get("anchor") is None else tuple(meta["anchor"])
        self.drift = None if meta.get("drift") is None else np.asarray(meta["drift"], float)
        if "prev_desc" in arrays:
            self.prev_sift = SiftFeatures(arrays["prev_kp"], arrays["prev_desc"])
        else:
            self.prev_sift = None
        self.prev_key = None

    def _carried(self, arrays: dict[str, np.ndarray], meta: dict, to_here,
                 ) -> tuple[dict[str, np.ndarray], dict]:
        """The particles and the last anchored position in this revision's frame; weights,
        velocities (local frames a few kilometres apart differ by hundredths of a degree)
        and the switching state as they were."""
        arrays = dict(arrays, pf_xy=to_here(arrays["pf_xy"]))
        if meta.get("anchor") is not None:
            clock, x, y = meta["anchor"]
            (x, y), = to_here([[x, y]])
            meta = dict(meta, anchor=[clock, float(x), float(y)])
        return arrays, meta

    def reset(self) -> None:
        self.pf.initialise()
        self.switch = SwitchState(switching.start(self.pinned))
        self.prev_sift, self.prev_key, self.last_time = None, None, None
        self.drift, self.anchor = None, None
        self.stats.pop("ever_tracked", None)

    def set_initial_pose(self, x: float, y: float, sigma: float = 5.0) -> None:
        self.pf.set_pose(x, y, sigma)
        self.drift, self.anchor = None, None
        self.switch = replace(self.switch, next=switching.start(self.pinned))
        self.prev_sift, self.prev_key = None, None

