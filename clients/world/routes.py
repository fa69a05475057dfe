"""Routes and the camera trajectories of the passes along them.

A route is a dense polyline (closed loop or open path) parameterised by arc length. Each
pass follows it with its own small deviations, as a robot driven round the same block six
times (Weiss et al. 2008, section V) or a quadcopter flown along the same route in gusty
wind (Erhard et al., section 5.1) would: a smooth lateral offset, a little heading jitter,
uneven speed, and a different start point within one frame spacing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Route:
    """A planar path.

    Attributes
    ----------
    points : (N, 2) float64 ndarray
        Dense vertices (east, north), about 5 cm apart.
    closed : bool
        Whether the path returns to its start (then the last vertex connects to the first).
    """

    points: np.ndarray
    closed: bool

    @property
    def cumulative(self) -> np.ndarray:
        pts = np.vstack([self.points, self.points[:1]]) if self.closed else self.points
        seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        return np.concatenate([[0.0], np.cumsum(seg)])

    @property
    def length(self) -> float:
        return float(self.cumulative[-1])

    def at(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Positions and unit tangents at arc lengths ``s`` (wrapped on closed routes).

        Returns
        -------
        xy : (M, 2) float64 ndarray
        tangent : (M, 2) float64 ndarray
        """
        pts = np.vstack([self.points, self.points[:1]]) if self.closed else self.points
        cum = self.cumulative
        s = np.asarray(s, np.float64)
        s = np.mod(s, cum[-1]) if self.closed else np.clip(s, 0.0, cum[-1])
        xy = np.stack([np.interp(s, cum, pts[:, 0]), np.interp(s, cum, pts[:, 1])], axis=1)
        ds = 0.25
        ahead = s + ds
        behind = s - ds
        if self.closed:
            ahead, behind = np.mod(ahead, cum[-1]), np.mod(behind, cum[-1])
        else:
            ahead, behind = np.clip(ahead, 0, cum[-1]), np.clip(behind, 0, cum[-1])
        d = (np.stack([np.interp(ahead, cum, pts[:, 0]), np.interp(ahead, cum, pts[:, 1])], 1)
             - np.stack([np.interp(behind, cum, pts[:, 0]), np.interp(behind, cum, pts[:, 1])], 1))
        tangent = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
        return xy, tangent


def rounded_rectangle(half_x: float, half_y: float, radius: float, step: float = 0.05) -> Route:
    """Closed counter-clockwise loop round a block, starting mid-way along its south side."""
    radius = min(radius, half_x, half_y)
    pieces = []
    corners = [(half_x - radius, -half_y + radius, -math.pi / 2),
               (half_x - radius, half_y - radius, 0.0),
               (-half_x + radius, half_y - radius, math.pi / 2),
               (-half_x + radius, -half_y + radius, math.pi)]
    start = np.array([0.0, -half_y])
    prev = start
    for cx, cy, a0 in corners:
        arc_start = np.array([cx + radius * math.cos(a0), cy + radius * math.sin(a0)])
        pieces.append(_line(prev, arc_start, step))
        n = max(2, int(math.ceil(radius * math.pi / 2 / step)))
        a = a0 + np.linspace(0.0, math.pi / 2, n, endpoint=False)
        pieces.append(np.stack([cx + radius * np.cos(a), cy + radius * np.sin(a)], axis=1))
        prev = np.array([cx + radius * math.cos(a0 + math.pi / 2),
                         cy + radius * math.sin(a0 + math.pi / 2)])
    pieces.append(_line(prev, start, step))
    return Route(np.concatenate(pieces), closed=True)


def lawnmower(width: float, height: float, lane_spacing: float, step: float = 0.05) -> Route:
    """Open back-and-forth survey path over ``[0, width] x [0, height]``, lanes along x
    joined by half circles, the pattern of a mapping flight."""
    n_lanes = max(2, int(math.floor(height / lane_spacing)) + 1)
    r = lane_spacing / 2
    pieces = []
    b = 0.0
    for k in range(n_lanes):
        y = k * lane_spacing
        a, b = (0.0, width) if k % 2 == 0 else (width, 0.0)
        pieces.append(_line(np.array([a, y]), np.array([b, y]), step))
        if k < n_lanes - 1:
            n = max(2, int(math.ceil(math.pi * r / step)))
            t = np.linspace(-math.pi / 2, math.pi / 2, n, endpoint=False)
            sign = 1.0 if k % 2 == 0 else -1.0
            pieces.append(np.stack([b + sign * r * np.cos(t), y + r + r * np.sin(t)], axis=1))
    end = np.array([[b, (n_lanes - 1) * lane_spacing]])
    return Route(np.concatenate(pieces + [end]), closed=False)


def _line(a: np.ndarray, b: np.ndarray, step: float) -> np.ndarray:
    n = max(1, int(math.ceil(np.linalg.norm(b - a) / step)))
    t = np.arange(n)[:, None] / n
    return a + t * (b - a)


def smooth_noise(rng: np.random.Generator, s: np.ndarray, wavelength: float,
                 amplitude: float, terms: int = 3) -> np.ndarray:
    """A smooth random function of arc length: a few sinusoids with random wavelengths
    (``wavelength / 2`` to ``2 wavelength``) and phases, scaled to ``amplitude`` at most."""
    s = np.asarray(s, np.float64)
    out = np.zeros_like(s)
    for _ in range(terms):
        lam = wavelength * 2.0 ** rng.uniform(-1.0, 1.0)
        out += np.sin(2 * math.pi * s / lam + rng.uniform(0, 2 * math.pi))
    return amplitude * out / terms


@dataclass(frozen=True)
class Trajectory:
    """Camera positions and headings of one pass.

    Attributes
    ----------
    s : (F,) float64 ndarray
        Arc length along the route of each frame (unwrapped).
    xy : (F, 2) float64 ndarray
        True positions (east, north).
    yaw : (F,) float64 ndarray
        Viewing direction, radians counter-clockwise from east.
    """

    s: np.ndarray
    xy: np.ndarray
    yaw: np.ndarray


def follow(route: Route, rng: np.random.Generator, *, frames: int, spacing: float,
           lateral_m: float, lateral_wavelength: float, speed_jitter: float,
           yaw_jitter_deg: float, start: float = 0.0) -> Trajectory:
    """Frames of one pass along ``route``.

    Parameters
    ----------
    frames : int
        Number of frames.
    spacing : float
        Mean distance between frames along the route (metres). On an open route the
        frames are then stretched to cover it from end to end.
    lateral_m : float
        Largest sideways deviation from the route (positive to the right of travel).
    lateral_wavelength : float
        Typical length over which the deviation changes (metres).
    speed_jitter : float
        Relative spread of the distance between consecutive frames (0.03 = 3 %).
    yaw_jitter_deg : float
        Largest heading deviation from the direction of travel.
    start : float
        Arc length of the first frame before the random start offset.
    """
    steps = spacing * np.clip(1.0 + speed_jitter * rng.standard_normal(frames), 0.2, 3.0)
    steps[0] = rng.uniform(0.0, spacing)     # passes start within one spacing of each other
    s = start + np.cumsum(steps)
    if not route.closed:
        # Open routes: scale so that the pass covers the route end to end.
        s = (s - s[0]) * ((route.length - 0.5) / max(s[-1] - s[0], 1e-9)) + 0.25
    base, tangent = route.at(s)
    normal = np.stack([tangent[:, 1], -tangent[:, 0]], axis=1)   # right of travel
    offset = smooth_noise(rng, s, lateral_wavelength, lateral_m * 0.6) + rng.uniform(
        -lateral_m * 0.4, lateral_m * 0.4)
    xy = base + offset[:, None] * normal
    # The heading follows the path actually driven, plus a small steering wobble.
    d_off = np.gradient(offset, s) if len(s) > 1 else np.zeros_like(s)
    heading = np.arctan2(tangent[:, 1], tangent[:, 0]) - np.arctan(d_off)
    yaw = heading + np.radians(smooth_noise(rng, s, 8.0, yaw_jitter_deg))
    return Trajectory(s=s, xy=xy, yaw=yaw)
