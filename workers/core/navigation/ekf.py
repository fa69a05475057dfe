"""Extended Kalman filter over the unicycle state ``(x, y, theta, v, omega)`` (Li et al.).

Li et al. smooth the visual pose fixes with an EKF "whose inputs and outputs are poses
(x, y, theta) and the dynamics are that of a wheeled mobile robot ... with state vector
augmented with velocities", so that measurement noise does not pass straight into the
control. The velocities follow a random walk (white acceleration noise); the pose moves by
the midpoint rule of eq. 6. Measurements are any subset of the state (a pose fix, a position
fix without heading, wheel odometry of ``(v, omega)``), with the angle innovation wrapped,
and bearings: the direction in which a known point (a taught camera) sees the robot.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .unicycle import wrap_angle

THETA = 2
POSE = (0, 1, 2)
POSITION = (0, 1)
VELOCITIES = (3, 4)


@dataclass(frozen=True)
class ProcessNoise:
    """Spectral densities of the process noise (variance per second).

    Attributes
    ----------
    accel : float
        Of the linear acceleration, (m/s^2)^2 s.
    ang_accel : float
        Of the angular acceleration, (rad/s^2)^2 s.
    pose : float
        Of unmodelled motion of the position (m^2/s; wheel slip).
    heading : float
        Of unmodelled rotation (rad^2/s).
    """

    accel: float = 0.05
    ang_accel: float = 0.2
    pose: float = 0.005
    heading: float = 0.002


def motion(state: np.ndarray, dt: float) -> np.ndarray:
    """The unicycle over ``dt`` at constant velocities (midpoint rule of Li eq. 6)."""
    x, y, th, v, w = state
    mid = th + 0.5 * w * dt
    return np.array([x + v * dt * math.cos(mid), y + v * dt * math.sin(mid),
                     wrap_angle(th + w * dt), v, w])


def motion_jacobian(state: np.ndarray, dt: float) -> np.ndarray:
    """(5, 5) Jacobian of :func:`motion` with respect to the state."""
    _, _, th, v, w = state
    mid = th + 0.5 * w * dt
    c, s = math.cos(mid), math.sin(mid)
    f = np.eye(5)
    f[0, 2], f[0, 3], f[0, 4] = -v * dt * s, dt * c, -0.5 * v * dt * dt * s
    f[1, 2], f[1, 3], f[1, 4] = v * dt * c, dt * s, 0.5 * v * dt * dt * c
    f[2, 4] = dt
    return f


class UnicycleEKF:
    """EKF over ``(x, y, theta, v, omega)``.

    Parameters
    ----------
    state : (5,) float
        Initial mean.
    cov : (5, 5) float
        Initial covariance.
    noise : ProcessNoise
    """

    def __init__(self, state, cov, noise: ProcessNoise | None = None) -> None:
        self.x = np.asarray(state, np.float64).copy()
        self.P = np.asarray(cov, np.float64).copy()
        if self.x.shape != (5,) or self.P.shape != (5, 5):
            raise ValueError("state must be (5,) and cov (5, 5)")
        self.x[THETA] = wrap_angle(self.x[THETA])
        self.noise = noise or ProcessNoise()

    def predict(self, dt: float) -> None:
        """Move the mean and covariance ``dt`` seconds forward."""
        if dt <= 0:
            return
        f = motion_jacobian(self.x, dt)
        n = self.noise
        q = np.diag([n.pose, n.pose, n.heading, n.accel, n.ang_accel]) * dt
        self.x = motion(self.x, dt)
        self.P = f @ self.P @ f.T + q

    def update(self, z, indices, R) -> float:
        """Fuse a measurement of the state components ``indices``.

        Parameters
        ----------
        z : (m,) float
        indices : sequence of m ints
            Which state components ``z`` measures (e.g. :data:`POSE`); the measurement
            model is linear, ``H`` picks those rows of the identity.
        R : (m, m) float
            Measurement covariance.

        Returns
        -------
        float
            The squared Mahalanobis distance of the innovation (for gating by the caller).
        """
        idx = list(indices)
        h = np.eye(5)[idx]
        innov = np.asarray(z, np.float64) - self.x[idx]
        if THETA in idx:
            k = idx.index(THETA)
            innov[k] = wrap_angle(innov[k])
        s = h @ self.P @ h.T + np.asarray(R, np.float64)
        gain = np.linalg.solve(s, h @ self.P).T             # P H^T S^-1; S symmetric
        self.x = self.x + gain @ innov
        self.x[THETA] = wrap_angle(self.x[THETA])
        # Joseph form keeps P symmetric and positive definite
        ikh = np.eye(5) - gain @ h
        self.P = ikh @ self.P @ ikh.T + gain @ np.asarray(R, np.float64) @ gain.T
        return float(innov @ np.linalg.solve(s, innov))

    def bearing_innovation(self, landmark, z: float, sigma: float, *, min_range: float = 0.3
                           ) -> tuple[float, np.ndarray, float] | None:
        """Innovation, Jacobian row and variance of a bearing measurement: the robot seen
        from ``landmark`` (x, y) in direction ``z`` (radians from east). None when the
        robot is predicted within ``min_range`` of the landmark, where a bearing says
        little."""
        dx, dy = self.x[0] - landmark[0], self.x[1] - landmark[1]
        r2 = dx * dx + dy * dy
        if r2 < min_range ** 2:
            return None
        h = np.zeros(5)
        h[0], h[1] = -dy / r2, dx / r2
        innov = float(wrap_angle(z - math.atan2(dy, dx)))
        return innov, h, float(h @ self.P @ h + sigma ** 2)

    def update_bearing(self, landmark, z: float, sigma: float, *, gate: float | None = None
                       ) -> bool:
        """Fuse a bearing measurement (see :meth:`bearing_innovation`); False when it was
        not fused (too close, or its squared Mahalanobis distance above ``gate``)."""
        found = self.bearing_innovation(landmark, z, sigma)
        if found is None:
            return False
        innov, h, s = found
        if gate is not None and innov * innov / s > gate:
            return False
        gain = self.P @ h / s
        self.x = self.x + gain * innov
        self.x[THETA] = wrap_angle(self.x[THETA])
        ikh = np.eye(5) - np.outer(gain, h)
        self.P = ikh @ self.P @ ikh.T + np.outer(gain, gain) * sigma ** 2
        return True

    def mahalanobis(self, z, indices, R) -> float:
        """The squared Mahalanobis distance a measurement would have, without fusing it."""
        idx = list(indices)
        innov = np.asarray(z, np.float64) - self.x[idx]
        if THETA in idx:
            k = idx.index(THETA)
            innov[k] = wrap_angle(innov[k])
        s = self.P[np.ix_(idx, idx)] + np.asarray(R, np.float64)
        return float(innov @ np.linalg.solve(s, innov))

    def to_dict(self) -> dict:
        return {"x": self.x.tolist(), "P": self.P.tolist()}

    @classmethod
    def from_dict(cls, d: dict, noise: ProcessNoise | None = None) -> UnicycleEKF:
        return cls(d["x"], d["P"], noise)
