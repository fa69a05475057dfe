"""Li et al.'s path-following law (eq. 8) with the paper's saturation of omega."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from .unicycle import wrap_angle


@dataclass(frozen=True)
class ControlConfig:
    """Gains and limits of the path-following law.

    Attributes
    ----------
    alpha : float
        Natural frequency of the closed loop per metre travelled (1/m): ``k2 = alpha^2``,
        ``k3 = 2 xi alpha`` (Li et al.). The law is continuous; applied once per frame, it
        wants ``alpha * v_max * dt`` under about 0.5 (at 0.6 m/s and one frame a second,
        alpha = 1 oscillates where 0.7 does not).
    xi : float
        Damping, ``1/sqrt(2)`` in the paper ("a small overshoot").
    v_max : float
        Forward speed when omega is not saturated (m/s).
    w_max : float
        Largest |omega| (rad/s); above it omega is saturated and v reduced to
        ``v_max * w_max / |omega|``.
    """

    alpha: float = 0.7
    xi: float = 1.0 / math.sqrt(2.0)
    v_max: float = 0.6
    w_max: float = 0.8

    def __post_init__(self) -> None:
        for name in ("alpha", "xi", "v_max", "w_max"):
            value = getattr(self, name)
            if not isinstance(value, int | float) or isinstance(value, bool) \
                    or not math.isfinite(value) or value <= 0:
                raise ValueError(f"{name} must be a positive number, got {value!r}")

    @property
    def k2(self) -> float:
        return self.alpha ** 2

    @property
    def k3(self) -> float:
        return 2.0 * self.xi * self.alpha

    def to_params(self) -> dict:
        return asdict(self)


def path_following_command(d: float, theta_err: float, curvature: float,
                           config: ControlConfig) -> tuple[float, float]:
    """Velocity command ``(v, omega)`` from the path errors (Li et al. eq. 8).

    ``omega = -k3 |v| th - k2 v d sin(th)/th + v cos(th) c / (1 - c d)`` at ``v = v_max``;
    when ``|omega| > w_max``, omega is saturated and ``v = v_max w_max / |omega|`` so that
    narrow turns do not lag.

    Parameters
    ----------
    d : float
        Signed distance to the path, positive left of it (m).
    theta_err : float
        Heading minus the path's heading at the reference point (rad).
    curvature : float
        Path curvature at the reference point (1/m).
    """
    th = float(wrap_angle(theta_err))
    v = config.v_max
    sinc = float(np.sinc(th / math.pi))          # sin(th)/th, 1 at th = 0
    # 1 - c d vanishes at the centre of curvature; hold it away from zero there
    denom = max(1.0 - curvature * d, 0.1)
    omega = -config.k3 * abs(v) * th - config.k2 * v * d * sinc + v * math.cos(th) * curvature / denom
    if abs(omega) > config.w_max:
        v = config.v_max * config.w_max / abs(omega)
        omega = math.copysign(config.w_max, omega)
    return v, omega
