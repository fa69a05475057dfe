"""The motion model: how particles move between two frames.

Weiss et al. 2008, IV-A step 2: without odometry each particle moves by a 2-D Gaussian
(sigma 4 m per frame) and then ``pull`` (0.2) of the way towards its nearest map image.
The map images lie on the routes the platform can take, so the pull keeps the cloud on them.

The sigma scales with the time between frames: ``hypot(sigma_floor, speed * dt)``; a robot
at 0.6 m/s one frame a second gets about the paper's 4 m, a UAV at 7 m/s five seconds apart
about 35 m. With a velocity in the state (constant-velocity model) the position moves by
``v * dt`` and both position and velocity diffuse; the position noise is then smaller because
the velocity carries the motion.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree


@dataclass(frozen=True)
class MotionModel:
    """Gaussian diffusion + pull, optionally with per-particle velocity.

    Attributes
    ----------
    sigma_floor : float
        Per-axis sigma (m) for one frame without timing, and the floor with timing.
    speed : float or None
        Typical speed (m/s); None: frames are assumed one ``nominal_dt`` apart.
    pull : float
    velocity : bool
    nominal_dt : float
        Seconds between frames assumed when a frame carries no time (the map's typical
        interval between captures, where known).
    """

    sigma_floor: float = 4.0
    speed: float | None = None
    pull: float = 0.2
    velocity: bool = False
    nominal_dt: float = 1.0

    def sigma(self, dt: float | None) -> float:
        """Per-axis position sigma (m) of a random-walk step over ``dt`` seconds."""
        if dt is None or self.speed is None or not np.isfinite(dt) or dt <= 0:
            if self.speed is None:
                return self.sigma_floor
            dt = self.nominal_dt
        return float(np.hypot(self.sigma_floor, self.speed * dt))

    def move(self, xy: np.ndarray, v: np.ndarray | None, dt: float | None,
             tree: cKDTree, map_xy: np.ndarray, rng: np.random.Generator, *,
             drift: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
        """Move particles by one step.

        Parameters
        ----------
        xy : (m, 2) float64 ndarray
        v : (m, 2) float64 ndarray or None
        dt : float or None
        tree, map_xy : nearest-neighbour structure and (N, 2) positions of the map images
        rng : numpy.random.Generator
        drift : (2,) float ndarray or None
            The platform's velocity (m/s) as the filter tracks it: every particle moves by
            ``drift * dt`` and the position noise halves, since the drift carries the motion.

        Returns
        -------
        xy, v : the moved particles (new arrays)
        """
        m = len(xy)
        sigma = self.sigma(dt)
        if self.velocity and v is not None and self.speed is not None:
            step_dt = self.nominal_dt if dt is None or not np.isfinite(dt) or dt <= 0 else dt
            # The velocity carries most of the motion; its change over a step is a fraction
            # of the speed (turns), the position noise the rest.
            v = v + rng.normal(0.0, 0.35 * self.speed, size=(m, 2))
            xy = xy + v * step_dt + rng.normal(0.0, 0.5 * sigma, size=(m, 2))
        elif drift is not None:
            step_dt = self.nominal_dt if dt is None or not np.isfinite(dt) or dt <= 0 else dt
            xy = xy + np.asarray(drift, np.float64) * step_dt \
                + rng.normal(0.0, 0.5 * sigma, size=(m, 2))
        else:
            xy = xy + rng.normal(0.0, sigma, size=(m, 2))
        if self.pull > 0 and len(map_xy):
            _, nearest = tree.query(xy)
            xy = xy + self.pull * (map_xy[nearest] - xy)
        return xy, v
