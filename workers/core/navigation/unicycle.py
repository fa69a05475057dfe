"""The wheeled unicycle of Li et al. eq. 6, integrated exactly, with actuation noise."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ActuationNoise:
    """How far the wheels do not do what they are told.

    The executed velocities are ``v (1 + e_v)`` and ``omega (1 + e_w) + b_w``, with ``e_v``,
    ``e_w`` drawn afresh each step from zero-mean normals of the given standard deviations
    and ``b_w`` an angular slip (rad/s) that does not scale with the command.
    """

    v_rel: float = 0.05
    omega_rel: float = 0.05
    omega_abs: float = 0.01

    def apply(self, v: float, omega: float, rng: np.random.Generator) -> tuple[float, float]:
        e = rng.standard_normal(3)
        return (v * (1.0 + self.v_rel * e[0]),
                omega * (1.0 + self.omega_rel * e[1]) + self.omega_abs * e[2])


def unicycle_step(pose: np.ndarray, v: float, omega: float, dt: float) -> np.ndarray:
    """Integrate ``x' = v cos(theta), y' = v sin(theta), theta' = omega`` over ``dt`` at
    constant velocities (Li eq. 6): an arc of radius ``v / omega``, or a straight line.

    Parameters
    ----------
    pose : (3,) float ndarray
        ``(x, y, theta)``, metres and radians.

    Returns
    -------
    (3,) float64 ndarray
        The pose after ``dt``; theta wrapped to (-pi, pi].
    """
    x, y, th = (float(p) for p in pose)
    dth = omega * dt
    if abs(dth) < 1e-9:
        x += v * dt * math.cos(th + dth / 2)
        y += v * dt * math.sin(th + dth / 2)
    else:
        r = v / omega
        x += r * (math.sin(th + dth) - math.sin(th))
        y -= r * (math.cos(th + dth) - math.cos(th))
    return np.array([x, y, wrap_angle(th + dth)])


def wrap_angle(a):
    """Angles wrapped to (-pi, pi]; works on floats and arrays."""
    return -((-np.asarray(a) + math.pi) % (2 * math.pi) - math.pi) if np.ndim(a) else \
        -((-float(a) + math.pi) % (2 * math.pi) - math.pi)
