"""Following a taught path: EKF-smoothed pose fixes in, Li et al.'s commands out."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from .control import ControlConfig, path_following_command
from .ekf import POSE, POSITION, VELOCITIES, ProcessNoise, UnicycleEKF
from .path import Path

CHI2_GATE = {1: 10.8, 2: 13.8, 3: 16.3}
"""99.9 % quantiles of chi-square with 1, 2 and 3 degrees of freedom: a fix further than this
from the filter's prediction is taken for a false recognition and not fused (Li et al.
trace the failures of Fig. 13 to false recognitions)."""
REACQUIRE = 3
"""After this many fixes in a row fall outside the gate, the filter is started again from the
last one. A gate protects a right estimate from a false recognition, but it also keeps a
wrong, overconfident estimate from ever hearing the fixes that would correct it: starting
1 m beside the path and 20 degrees off, such a filter drove the robot several metres away
while the fixes said where it was."""


@dataclass(frozen=True)
class FollowerConfig:
    """Parameters of path following.

    Attributes
    ----------
    control : ControlConfig
    dt : float
        Seconds between frames when their capture times do not say.
    arrive_tolerance : float
        Arrived when the reference point is this close to the end of the path (m).
    command_sigma_v, command_sigma_w : float
        Standard deviations of the executed velocities about the command, with which the
        last command is fused as a measurement of ``(v, omega)``.
    heading_sigma : float
        Heading standard deviation (rad) assumed for a fix that carries a heading.
    gate : bool
        Whether to reject fixes outside :data:`CHI2_GATE`; the first fixes after a start are
        always fused.
    """

    control: ControlConfig = ControlConfig()
    dt: float = 1.0
    arrive_tolerance: float = 0.5
    command_sigma_v: float = 0.05
    command_sigma_w: float = 0.05
    heading_sigma: float = math.radians(10.0)
    gate: bool = True

    @classmethod
    def from_params(cls, params: dict) -> FollowerConfig:
        params = dict(params)
        control = ControlConfig(**{k: params.pop(k) for k in ("alpha", "v_max", "w_max", "xi")
                                   if k in params})
        unknown = set(params) - {"dt", "arrive_tolerance", "command_sigma_v", "command_sigma_w",
                                 "heading_sigma", "gate"}
        if unknown:
            raise ValueError(f"unknown navigation parameter(s): {', '.join(sorted(unknown))}")
        return cls(control=control, **params)

    def to_params(self) -> dict:
        d = asdict(self)
        d.update(d.pop("control"))
        return d


@dataclass(frozen=True, slots=True)
class NavigationStep:
    """What path following says after one frame.

    ``state`` is the EKF mean ``(x, y, theta, v, omega)``; ``command`` the velocities to
    drive ``(v, omega)``; ``reference`` the reference point ``(x, y, theta)``; ``d`` and
    ``theta_error`` the errors the command came from; ``node`` the topological node of the
    reference point; ``progress`` the metres of path behind the reference point and
    ``length`` the whole; ``fused`` whether this frame's fix was used.
    """

    state: tuple[float, float, float, float, float]
    command: tuple[float, float]
    reference: tuple[float, float, float]
    d: float
    theta_error: float
    curvature: float
    node: int
    progress: float
    length: float
    arrived: bool
    fused: bool

    def to_dict(self) -> dict:
        return {"state": dict(zip(("x", "y", "theta", "v", "omega"), self.state, strict=True)),
                "command": {"v": self.command[0], "omega": self.command[1]},
                "reference": dict(zip(("x", "y", "theta"), self.reference, strict=True)),
                "cross_track": self.d, "heading_error": self.theta_error,
                "curvature": self.curvature, "node": self.node, "progress": self.progress,
                "length": self.length, "arrived": self.arrived, "fused": self.fused}


class PathFollower:
    """Follows ``path``: fuse a fix, project, command.

    Parameters
    ----------
    path : Path
    node_s : (K,) float ndarray
        Arc length at which each topological node begins (ascending, first 0).
    config : FollowerConfig
    """

    def __init__(self, path: Path, node_s, config: FollowerConfig | None = None) -> None:
        self.path = path
        self.node_s = np.asarray(node_s, np.float64)
        self.config = config or FollowerConfig()
        self.ekf: UnicycleEKF | None = None
        self.s = 0.0
        self.command = (0.0, 0.0)
        self.arrived = False
        self.last_time: float | None = None
        self.fixes = 0
        self.rejected = 0

    def step(self, xy, position_cov, *, heading: float | None = None,
             heading_sigma: float | None = None, bearings=(),
             captured_at: float | None = None) -> NavigationStep | None:
        """One frame's pose fix in, one command out.

        Parameters
        ----------
        xy : (2,) float or None
            The localiser's position; None when it has none this frame (the filter then
            only predicts; before the first fix there is nothing to say and None is
            returned).
        position_cov : (2, 2) float
            Its covariance (m^2).
        heading : float, optional
            The robot's heading (radians counter-clockwise from east) where the localiser
            gave one.
        heading_sigma : float, optional
            Its standard deviation (radians); :attr:`FollowerConfig.heading_sigma` without.
        bearings : sequence of (x, y, bearing, sigma)
            Directions (radians from east) in which known points see the robot, each fused
            after the fix (and gated like it).
        captured_at : float, optional
            Capture time (s); the time step is :attr:`FollowerConfig.dt` without it.
        """
        cfg = self.config
        dt = cfg.dt
        if captured_at is not None and self.last_time is not None and captured_at > self.last_time:
            dt = captured_at - self.last_time
        if captured_at is not None:
            self.last_time = captured_at
        if xy is None:
            # no fix this frame (the localiser is still initialising or lost): dead-reckon
            if self.ekf is None:
                return None
            self._predict(dt)
            return self._command(False, dt)
        z = np.asarray(xy, np.float64)
        cov = np.asarray(position_cov, np.float64)
        fused = True
        if self.ekf is None:
            self._start(z, cov, heading)
        else:
            ekf = self.ekf
            self._predict(dt)
            if heading is not None:
                zz, idx = np.r_[z, heading], POSE
                r = np.zeros((3, 3))
                r[:2, :2] = cov
                r[2, 2] = (cfg.heading_sigma if heading_sigma is None else heading_sigma) ** 2
            else:
                zz, idx, r = z, POSITION, cov
            fused = not cfg.gate or self.fixes < 3 or ekf.mahalanobis(zz, idx, r) <= CHI2_GATE[len(idx)]
            self.rejected = 0 if fused else self.rejected + 1
            if self.rejected >= REACQUIRE:
                self._start(z, cov, heading, velocities=ekf.x[3:])
                self.rejected, fused = 0, True
            elif fused:
                ekf.update(zz, idx, r)
                for lx, ly, bearing, sigma in bearings:
                    ekf.update_bearing((lx, ly), bearing, sigma,
                                       gate=CHI2_GATE[1] if cfg.gate else None)
        if fused:
            self.fixes += 1
        return self._command(fused, dt)

    def _predict(self, dt: float) -> None:
        """Fuse the last command as what the wheels did since the last frame, then move the
        filter on by ``dt`` at those velocities.

        The command comes first: it is what the robot drove during the interval. Predicting
        at the velocities of the frame before and fusing the command only afterwards left the
        heading one command behind, 30-45 degrees on a sharp correction, so the law steered
        on a stale heading and overshot.
        """
        cfg = self.config
        self.ekf.update(self.command, VELOCITIES,
                        np.diag([cfg.command_sigma_v ** 2, cfg.command_sigma_w ** 2]))
        self.ekf.predict(dt)

    def _start(self, z: np.ndarray, cov: np.ndarray, heading: float | None,
               velocities=(0.0, 0.0)) -> None:
        proj = self.path.project(z)
        self.s = proj.s
        theta = proj.theta if heading is None else heading
        # without a heading, start along the path, but not sure of it
        th_var = self.config.heading_sigma ** 2 if heading is not None else math.radians(30) ** 2
        p0 = np.zeros((5, 5))
        p0[:2, :2] = cov
        p0[2, 2], p0[3, 3], p0[4, 4] = th_var, 0.1, 0.1
        self.ekf = UnicycleEKF([z[0], z[1], theta, *velocities], p0, ProcessNoise())

    def _command(self, fused: bool, dt: float) -> NavigationStep:
        x = self.ekf.x
        # search as far ahead as the robot can have gone since the last frame, and more
        reach = 10.0 + 3.0 * max(abs(float(x[3])), self.config.control.v_max) * dt
        proj = self.path.project(x[:2], s_hint=self.s, window=reach)
        self.s = max(self.s, proj.s) if self.arrived else proj.s
        theta_err = math.atan2(math.sin(x[2] - proj.theta), math.cos(x[2] - proj.theta))
        if self.s >= self.path.length - self.config.arrive_tolerance:
            self.arrived = True
        self.command = (0.0, 0.0) if self.arrived else path_following_command(
            proj.d, theta_err, proj.curvature, self.config.control)
        node = int(np.searchsorted(self.node_s, self.s, side="right") - 1)
        return NavigationStep(state=tuple(float(v) for v in x), command=self.command,
                              reference=(proj.x, proj.y, proj.theta), d=proj.d,
                              theta_error=theta_err, curvature=proj.curvature,
                              node=max(node, 0), progress=self.s, length=self.path.length,
                              arrived=self.arrived, fused=fused)

    # -- checkpointing ----------------------------------------------------------------------

    def get_state(self) -> dict:
        return {"ekf": None if self.ekf is None else self.ekf.to_dict(), "s": self.s,
                "command": list(self.command), "arrived": self.arrived,
                "last_time": self.last_time, "fixes": self.fixes, "rejected": self.rejected}

    def set_state(self, state: dict) -> None:
        self.ekf = None if state["ekf"] is None else UnicycleEKF.from_dict(state["ekf"])
        self.s = float(state["s"])
        self.command = tuple(state["command"])
        self.arrived = bool(state["arrived"])
        self.last_time = state["last_time"]
        self.fixes = int(state["fixes"])
        self.rejected = int(state.get("rejected", 0))
