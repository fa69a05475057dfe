"""One particle filter: particle arrays, the step of Weiss IV-A and the switch of IV-B.

A step, in the paper's order:

1. resample by weight;
2. move (motion model: Gaussian, pull towards the nearest map image);
3. weight by the similarity of the frame with each particle's nearest map image (computed
   once per distinct map image) times the distance factor; power 20 for global features;
   normalise;
4. estimate: weighted mean and covariance; sigma_x, sigma_y by eq. 2;
5. decide the next step's features (IV-B);
6. replace the worst 5 % by new particles with weight 1/m; renormalise.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .config import REFERENCE_SIGMA, FilterConfig
from .measurement import log_likelihoods, normalise_log, position_log_likelihoods
from .motion import MotionModel
from .resampling import RESAMPLERS

SIFT = "sift"
GLOBAL = "global"

SimilarityFn = Callable[[np.ndarray], np.ndarray]
"""Map-image indexes (k,) -> similarities (k,) in [0, 1] of the current frame."""

PositionFix = tuple[np.ndarray, float]
"""A metric position measurement: east/north (2,) and its sigma per axis (m)."""

RefineFn = Callable[[np.ndarray, np.ndarray], "PositionFix | None"]
"""(scored map images, their similarities) -> a position measurement of the frame, or None."""


@dataclass(frozen=True)
class CloudStats:
    """Estimate statistics of the particle cloud after the weight update."""

    mean: np.ndarray  # (2,)
    cov: np.ndarray  # (2, 2)
    sigma_x: float
    sigma_y: float


def cloud_stats(xy: np.ndarray, w: np.ndarray) -> CloudStats:
    """Weighted mean, covariance and the standard deviations of Weiss eq. 2.

    Parameters
    ----------
    xy : (m, 2) float ndarray
    w : (m,) float ndarray, summing to 1
    """
    mean = w @ xy
    d = xy - mean
    cov = (d * w[:, None]).T @ d
    return CloudStats(mean, cov, float(np.sqrt(max(cov[0, 0], 0.0))),
                      float(np.sqrt(max(cov[1, 1], 0.0))))


class ParticleFilter:
    """The particle filter over a map's image positions.

    Parameters
    ----------
    map_xy : (N, 2) float ndarray
        East/north positions of the map images.
    tree : scipy.spatial.cKDTree over ``map_xy``
    config : FilterConfig
    motion : MotionModel
    distance_scale : float
        Length scale (m) of the distance factor.
    rng : numpy.random.Generator
        The only source of randomness; its state is part of the filter's state.
    """

    def __init__(self, map_xy: np.ndarray, tree, config: FilterConfig, motion: MotionModel,
                 distance_scale: float, rng: np.random.Generator) -> None:
        self.map_xy = np.asarray(map_xy, dtype=np.float64)
        self.tree = tree
        self.config = config
        self.motion = motion
        self.distance_scale = float(distance_scale)
        self.rng = rng
        lo, hi = self.map_xy.min(axis=0), self.map_xy.max(axis=0)
        # Uniform particles cover the map's extent plus a margin of one distance scale,
        # so positions just beyond the outermost images stay reachable.
        self.bounds = (lo - self.distance_scale, hi + self.distance_scale)
        self.mode = SIFT
        self.steps = 0
        self.converged = False
        self.last_fix: PositionFix | None = None
        self.initialise()

    # -- state ---------------------------------------------------------------------------

    def initialise(self) -> None:
        """Global (re-)initialisation: m particles uniform over the map, weight 1/m."""
        m = self.config.n_particles
        self.xy = self._uniform(m)
        self.v = self._random_velocity(m)
        self.w = np.full(m, 1.0 / m)
        self.mode = SIFT  # Weiss IV-B: the first step always uses SIFT
        self.converged = False

    def set_pose(self, x: float, y: float, sigma: float) -> None:
        """Particles around a known pose (AMCL's set_initial_pose)."""
        m = self.config.n_particles
        self.xy = np.array([x, y], dtype=np.float64) + self.rng.normal(0.0, sigma, size=(m, 2))
        self.v = self._random_velocity(m)
        self.w = np.full(m, 1.0 / m)
        self.mode = SIFT
        self.converged = False

    def _uniform(self, k: int) -> np.ndarray:
        lo, hi = self.bounds
        return lo + self.rng.random((k, 2)) * (hi - lo)

    def _random_velocity(self, k: int) -> np.ndarray | None:
        if not self.config.velocity or self.motion.speed is None:
            return None
        angle = self.rng.random(k) * 2.0 * np.pi
        return self.motion.speed * np.stack([np.cos(angle), np.sin(angle)], axis=1)

    def thresholds(self) -> tuple[float, float]:
        """(d_global, d_sift) scaled to the motion sigma between frames a nominal gap apart.

        The nominal gap, not the last one: after a long gap the cloud is spread because the
        platform could be anywhere, and that is exactly when SIFT is needed.
        """
        k = self.motion.sigma(None) / REFERENCE_SIGMA
        return self.config.d_global * k, self.config.d_sift * k

    # -- one step ------------------------------------------------------------------------

    def step(self, similarity: SimilarityFn, dt: float | None, *,
             all_similarities: bool = False, candidates: np.ndarray | None = None,
             refine: RefineFn | None = None,
             ) -> tuple[CloudStats, str, np.ndarray, np.ndarray]:
        """Run one filter step with the feature type in ``self.mode``.

        Parameters
        ----------
        similarity : callable
            Map-image indexes -> similarities in [0, 1] for the current frame, using the
            features of ``self.mode``.
        dt : float or None
            Seconds since the previous frame.
        all_similarities : bool
            Ask for every map image's similarity (cheap for global features), which lets
            replacement particles start at the best retrieved images.
        candidates : (c,) int ndarray or None
            Further map images to score besides the particles' nearest ones (e.g. the best
            global matches, shortlisted for SIFT), so replacement particles can start there.
        refine : callable or None
            Called with the scored map images and their similarities; a position it
            returns is fused as a second measurement (:func:`position_log_likelihoods`)
            and seeds a quarter of the replacement particles. ``self.last_fix`` keeps it.

        Returns
        -------
        stats : CloudStats
        used : str
            The feature type this step used.
        scored : (k,) int ndarray
            Map images whose similarity was computed.
        sims : (k,) float ndarray
            Their similarities.
        """
        cfg = self.config
        used = self.mode
        # 1. resample
        idx = RESAMPLERS[cfg.resampler](self.w, self.rng)
        self.xy = self.xy[idx]
        if self.v is not None:
            self.v = self.v[idx]
        # 2. move
        self.xy, self.v = self.motion.move(self.xy, self.v, dt, self.tree, self.map_xy,
                                           self.rng)
        # 3. weight: one similarity per distinct nearest map image
        dist, nearest = self.tree.query(self.xy)
        if all_similarities:
            scored = np.arange(len(self.map_xy))
            sims = np.asarray(similarity(scored), dtype=np.float64)
            per_particle = sims[nearest]
        else:
            scored = np.unique(nearest if candidates is None
                               else np.concatenate([nearest, candidates]))
            sims = np.asarray(similarity(scored), dtype=np.float64)
            per_particle = sims[np.searchsorted(scored, nearest)]
        power = cfg.global_power if used == GLOBAL else cfg.sift_power
        logw = log_likelihoods(per_particle, dist, power=power, scale=self.distance_scale)
        self.last_fix = refine(scored, sims) if refine is not None else None
        if self.last_fix is not None:
            # Both measurements come from one frame but from different evidence (which
            # place it looks like; where its camera is): their likelihoods multiply.
            # Without any similar image the position alone still weighs the particles.
            base = logw if np.isfinite(logw).any() else np.zeros_like(logw)
            logw = base + position_log_likelihoods(self.xy, self.last_fix[0],
                                                   self.last_fix[1],
                                                   outlier=cfg.refine_outlier)
        w = normalise_log(logw)
        # No image looked anything like the frame: the measurement says nothing, so the
        # predicted cloud stands with uniform weights.
        self.w = np.full(len(self.xy), 1.0 / len(self.xy)) if w is None else w
        # 4. estimate
        stats = cloud_stats(self.xy, self.w)
        # 5. decide the next step's features (IV-B)
        d_global, d_sift = self.thresholds()
        spread = max(stats.sigma_x, stats.sigma_y)
        if used == SIFT:
            self.mode = GLOBAL if spread < d_sift else SIFT
        else:
            self.mode = SIFT if spread > d_global else GLOBAL
            if self.mode == GLOBAL and cfg.global_check and len(scored) == len(self.map_xy):
                top = np.argsort(-sims, kind="stable")[: cfg.global_check]
                gap = np.min(np.linalg.norm(self.map_xy[scored[top]] - stats.mean, axis=1))
                if gap > d_global:
                    self.mode = SIFT
        if spread < d_sift:
            self.converged = True
        # 6. replace the worst particles
        self._replace_worst(scored, sims, power)
        self.steps += 1
        return stats, used, scored, sims

    def _replace_worst(self, scored: np.ndarray, sims: np.ndarray, power: float) -> None:
        m = len(self.w)
        k = int(round(self.config.replace_fraction * m))
        if k == 0:
            return
        worst = np.argpartition(self.w, k - 1)[:k]
        new_xy = self._uniform(k)
        if self.config.replacement == "retrieval" and len(scored):
            # Sensor resetting: half of the new particles start near map images drawn by
            # their similarity to the frame, so a lost filter finds its way back quickly.
            prob = normalise_log(power * np.log(np.clip(sims, 1e-300, 1.0)))
            if prob is not None:
                half = k // 2
                pick = scored[self.rng.choice(len(scored), size=half, p=prob)]
                new_xy[:half] = self.map_xy[pick] + self.rng.normal(
                    0.0, 0.5 * self.distance_scale, size=(half, 2))
        if self.last_fix is not None:
            # Sensor resetting at the measured position: a filter that lost the platform
            # comes back at once when a pose is solved.
            quarter = k // 4
            xy, sigma = self.last_fix
            new_xy[k - quarter:] = xy + self.rng.normal(0.0, sigma, size=(quarter, 2))
        self.xy[worst] = new_xy
        if self.v is not None:
            self.v[worst] = self._random_velocity(k)
        self.w[worst] = 1.0 / m
        # renormalise: the new particles changed the sum
        self.w /= self.w.sum()

    # -- serialisation -------------------------------------------------------------------

    def state(self) -> tuple[dict[str, np.ndarray], dict]:
        arrays = {"xy": self.xy, "w": self.w}
        if self.v is not None:
            arrays["v"] = self.v
        meta = {"mode": self.mode, "steps": self.steps, "converged": self.converged,
                "rng": self.rng.bit_generator.state}
        return arrays, meta

    def load(self, arrays: dict[str, np.ndarray], meta: dict) -> None:
        self.xy = np.array(arrays["xy"], dtype=np.float64)
        self.w = np.array(arrays["w"], dtype=np.float64)
        self.v = np.array(arrays["v"], dtype=np.float64) if "v" in arrays else None
        self.mode = meta["mode"]
        self.steps = int(meta["steps"])
        self.converged = bool(meta["converged"])
        self.rng.bit_generator.state = meta["rng"]
