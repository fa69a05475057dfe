"""One particle filter: particle arrays and the step of Weiss et al. 2008, IV-A.

A step, in the paper's order:

1. resample by weight;
2. move (motion model: Gaussian, pull towards the nearest map image);
3. weight by the measurements (:mod:`.measurement`; the paper's is the frame's similarity
   with each particle's nearest map image times the distance factor, power 20 for global
   features); normalise;
4. estimate: weighted mean and covariance; sigma_x, sigma_y by eq. 2 (and, under
   ``point_estimate="cluster"``, the mean and spread of the heaviest cluster where it holds
   most of the weight: :mod:`.clusters`);
5. (the next step's features are the localiser's choice: :mod:`.switching`, IV-B);
6. replace the worst 5 % by new particles with weight 1/m; renormalise.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from .clusters import heaviest_cluster
from .config import FilterConfig
from .measurement import Likelihood, Measurement, Position, normalise_log
from .motion import MotionModel
from .resampling import RESAMPLERS

RefineFn = Callable[[tuple[Likelihood, ...]], "Position | None"]
"""What the measurements said -> a metric position of the frame, or None."""


@dataclass(frozen=True)
class CloudStats:
    """Estimate statistics of the particle cloud after the weight update."""

    mean: np.ndarray  # (2,)
    cov: np.ndarray  # (2, 2)
    sigma_x: float
    sigma_y: float

    @property
    def spread(self) -> float:
        """``max(sigma_x, sigma_y)``: what the switching rule compares with its thresholds."""
        return max(self.sigma_x, self.sigma_y)


def cloud_stats(xy: np.ndarray, w: np.ndarray, about: np.ndarray | None = None) -> CloudStats:
    """Weighted mean, covariance and the standard deviations of Weiss eq. 2.

    Parameters
    ----------
    xy : (m, 2) float ndarray
    w : (m,) float ndarray, summing to 1
    about : (2,) float ndarray, optional
        Another position to report, the covariance then being the cloud's second moment
        about it (never smaller than that about the mean).
    """
    mean = w @ xy if about is None else np.asarray(about, np.float64)
    d = xy - mean
    cov = (d * w[:, None]).T @ d
    return CloudStats(mean, cov, float(np.sqrt(max(cov[0, 0], 0.0))),
                      float(np.sqrt(max(cov[1, 1], 0.0))))


CLOUD_SAMPLE = 64
"""Particles an estimate carries for display: enough to show the cloud's shape, small enough
to stream ten times a second."""


def cloud_sample(xy: np.ndarray, w: np.ndarray, k: int = CLOUD_SAMPLE) -> np.ndarray:
    """``k`` particles drawn in proportion to their weights, without randomness.

    Systematic selection at the fixed offsets ``(i + 0.5) / k`` of the cumulative weights: a
    particle of weight ``w`` is chosen about ``k * w`` times, and the same cloud always gives
    the same sample, so drawing it leaves the filter's random stream untouched.

    Parameters
    ----------
    xy : (m, 2) float ndarray
    w : (m,) float ndarray, non-negative, not all zero
    k : int
        Sample size; a cloud of at most ``k`` particles is returned whole.

    Returns
    -------
    (min(k, m), 2) float ndarray
    """
    if len(xy) <= k:
        return np.asarray(xy, dtype=float).copy()
    cum = np.cumsum(w, dtype=float)
    targets = (np.arange(k) + 0.5) / k * cum[-1]
    # clip: rounding can leave the last target a hair above the final cumulative weight
    idx = np.minimum(np.searchsorted(cum, targets, side="right"), len(xy) - 1)
    return np.asarray(xy, dtype=float)[idx]


@dataclass(frozen=True)
class StepResult:
    """What one filter step produced.

    Attributes
    ----------
    stats : CloudStats
        The weighted cloud before replacement: its mean, covariance and spread.
    likelihoods : tuple of Likelihood
        One per measurement, in the order given.
    estimate : CloudStats
        What the step reports (``config.point_estimate``): ``stats`` itself, or, where the
        cloud's heaviest cluster holds most of the weight, that cluster's mean with the
        cloud's covariance about it.
    spread : float
        What the switching rule and the tracking status judge: the cloud's spread (Weiss
        IV-B), or that of the cluster ``estimate`` reports, where it reports one.
    """

    stats: CloudStats
    likelihoods: tuple[Likelihood, ...]
    estimate: CloudStats
    spread: float

    @property
    def kinds(self) -> tuple[str, ...]:
        """The kinds of measurement the step used."""
        return tuple(lk.kind for lk in self.likelihoods)


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
    spacing : float, optional
        The map images' typical spacing (m), the scale of the cloud's clusters under
        ``point_estimate="cluster"``: the cells are an eighth of a spacing across the
        diagonal (two touching cells hold particles at most one spacing apart) and never
        narrower than the motion's floor (one step spreads a hypothesis that far; finer
        cells would split it into fragments, as on the robot world, whose images lie half a
        metre apart). The distance scale where not given.
    """

    def __init__(self, map_xy: np.ndarray, tree, config: FilterConfig, motion: MotionModel,
                 distance_scale: float, rng: np.random.Generator, *,
                 spacing: float | None = None) -> None:
        self.map_xy = np.asarray(map_xy, dtype=np.float64)
        self.tree = tree
        self.config = config
        self.motion = motion
        self.distance_scale = float(distance_scale)
        self.rng = rng
        scale = spacing if spacing is not None and spacing > 0 else self.distance_scale
        # a cell's diagonal neighbour is at most 2 * sqrt(2) cells away
        self.cluster_cell = max(scale / (2.0 * np.sqrt(2.0)), motion.sigma_floor)
        lo, hi = self.map_xy.min(axis=0), self.map_xy.max(axis=0)
        # Uniform particles cover the map's extent plus a margin of one distance scale,
        # so positions just beyond the outermost images stay reachable.
        self.bounds = (lo - self.distance_scale, hi + self.distance_scale)
        self.steps = 0
        self.initialise()

    # -- state ---------------------------------------------------------------------------

    def initialise(self) -> None:
        """Global (re-)initialisation: m particles uniform over the map, weight 1/m."""
        m = self.config.n_particles
        self.xy = self._uniform(m)
        self.v = self._random_velocity(m)
        self.w = np.full(m, 1.0 / m)

    def set_pose(self, x: float, y: float, sigma: float) -> None:
        """Particles around a known pose (AMCL's set_initial_pose)."""
        m = self.config.n_particles
        self.xy = np.array([x, y], dtype=np.float64) + self.rng.normal(0.0, sigma, size=(m, 2))
        self.v = self._random_velocity(m)
        self.w = np.full(m, 1.0 / m)

    def snapshot(self) -> tuple:
        """The cloud as it is, for :meth:`restore` (a step taken and then taken back)."""
        return (self.xy.copy(), self.w.copy(), None if self.v is None else self.v.copy(),
                self.steps)

    def restore(self, snapshot: tuple) -> None:
        self.xy, self.w, self.v, self.steps = snapshot

    def _uniform(self, k: int) -> np.ndarray:
        lo, hi = self.bounds
        return lo + self.rng.random((k, 2)) * (hi - lo)

    def _random_velocity(self, k: int) -> np.ndarray | None:
        if not self.config.motion.velocity or self.motion.speed is None:
            return None
        angle = self.rng.random(k) * 2.0 * np.pi
        return self.motion.speed * np.stack([np.cos(angle), np.sin(angle)], axis=1)

    # -- one step ------------------------------------------------------------------------

    def step(self, measurements: Sequence[Measurement], dt: float | None, *,
             refine: RefineFn | None = None, drift: np.ndarray | None = None) -> StepResult:
        """Run one filter step.

        Parameters
        ----------
        measurements : sequence of Measurement, at least one
            What was measured of the current frame; their likelihoods multiply.
        dt : float or None
            Seconds since the previous frame.
        refine : callable or None
            Given the measurements' likelihoods, a metric position of the frame (or None).
            A position is a further measurement, and a share of the particles
            (``config.refine.inject``) is first drawn around it: sensor resetting
            (Lenser and Veloso 2000), so the posterior has particles where the position
            says the platform is even when the motion spread the cloud thin. A position
            marked ``alone`` takes the place of the first measurement (the frame's image
            similarity) in the weights.
        drift : (2,) float ndarray or None
            The platform's tracked velocity (m/s) for the motion step
            (:meth:`MotionModel.move`).

        Returns
        -------
        StepResult
        """
        cfg = self.config
        # 1. resample
        idx = RESAMPLERS[cfg.resampler](self.w, self.rng)
        self.xy = self.xy[idx]
        if self.v is not None:
            self.v = self.v[idx]
        # 2. move
        self.xy, self.v = self.motion.move(self.xy, self.v, dt, self.tree, self.map_xy,
                                           self.rng, drift=drift)
        # 3. weight
        likelihoods = tuple(m.likelihood(self.xy, self.tree) for m in measurements)
        position = refine(likelihoods) if refine is not None else None
        if position is not None:
            k = int(round(cfg.refine.inject * len(self.xy)))
            if k:
                drawn = self.rng.choice(len(self.xy), size=k, replace=False)
                self.xy[drawn] = position.xy + self.rng.normal(0.0, position.sigma,
                                                               size=(k, 2))
                likelihoods = tuple(m.likelihood(self.xy, self.tree) for m in measurements)
            likelihoods = likelihoods + (position.likelihood(self.xy, self.tree),)
        weighing = likelihoods[1:] if position is not None and position.alone else likelihoods
        logw = weighing[0].log
        for other in weighing[1:]:
            logw = logw + other.log
        w = normalise_log(logw)
        # No particle is possible under the measurements: they say nothing, so the
        # predicted cloud stands with uniform weights.
        self.w = np.full(len(self.xy), 1.0 / len(self.xy)) if w is None else w
        # 4. estimate
        stats = cloud_stats(self.xy, self.w)
        estimate, spread = stats, stats.spread
        if cfg.point_estimate == "cluster":
            members, share = heaviest_cluster(self.xy, self.w, self.cluster_cell)
            if share > 0.5:  # a hypothesis holding most of the weight
                own = cloud_stats(self.xy[members], self.w[members] / self.w[members].sum())
                estimate = cloud_stats(self.xy, self.w, about=own.mean)
                spread = own.spread
        # 6. replace the worst particles
        self._replace_worst(likelihoods)
        self.steps += 1
        return StepResult(stats, likelihoods, estimate, spread)

    def _replace_worst(self, likelihoods: tuple[Likelihood, ...]) -> None:
        m = len(self.w)
        k = int(round(self.config.reset.fraction * m))
        if k == 0:
            return
        worst = np.argpartition(self.w, k - 1)[:k]
        new_xy = self._uniform(k)
        images = next((lk for lk in likelihoods if len(lk.scored)), None)
        if self.config.reset.replacement == "retrieval" and images is not None:
            # Sensor resetting: half of the new particles start near map images drawn by
            # their similarity to the frame, so a lost filter finds its way back quickly.
            prob = normalise_log(images.power * np.log(np.clip(images.similarities, 1e-300,
                                                               1.0)))
            if prob is not None:
                half = k // 2
                pick = images.scored[self.rng.choice(len(images.scored), size=half, p=prob)]
                new_xy[:half] = self.map_xy[pick] + self.rng.normal(
                    0.0, 0.5 * self.distance_scale, size=(half, 2))
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
        meta = {"steps": self.steps, "rng": self.rng.bit_generator.state}
        return arrays, meta

    def load(self, arrays: dict[str, np.ndarray], meta: dict) -> None:
        self.xy = np.array(arrays["xy"], dtype=np.float64)
        self.w = np.array(arrays["w"], dtype=np.float64)
        self.v = np.array(arrays["v"], dtype=np.float64) if "v" in arrays else None
        self.steps = int(meta["steps"])
        self.rng.bit_generator.state = meta["rng"]
