"""The taught path: arc length, heading, curvature, and the reference point (Li eq. 7)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter1d

from .unicycle import wrap_angle

STEP = 0.05
"""Metres between the vertices of a resampled path."""


@dataclass(frozen=True, slots=True)
class Projection:
    """Where a position lies relative to the path.

    Attributes
    ----------
    s : float
        Arc length of the reference point, metres from the start.
    x, y, theta : float
        The reference point (Li eq. 7: the closest point of the path) and the path's heading
        there, radians counter-clockwise from east.
    d : float
        Signed distance to the path, ``[x - x_ref, y - y_ref] . n`` with ``n`` the unit
        normal to the left of travel: positive left of the path.
    curvature : float
        ``c(s) = d theta / ds`` at the reference point, 1/metres, positive turning left.
    """

    s: float
    x: float
    y: float
    theta: float
    d: float
    curvature: float


class Path:
    """A planar path resampled every :data:`STEP` metres.

    Parameters
    ----------
    points : (N, 2) float ndarray
        Positions in driving order (east, north), metres; consecutive duplicates are dropped.
    smoothing : float
        Standard deviation in metres of the Gaussian the vertices are smoothed with before
        headings and curvature are taken (Li: "it is important to have smooth trajectories"
        or the control saturates); 0 keeps them as given.
    """

    AMBIGUITY_M = 1.0
    """Without a hint, a passage of the path this much further than the closest one
    still counts as close, and the earliest close one wins."""

    def __init__(self, points: np.ndarray, *, smoothing: float = 1.0) -> None:
        pts = np.asarray(points, np.float64)
        if pts.ndim != 2 or pts.shape[1] != 2 or not np.isfinite(pts).all():
            raise ValueError("points must be a finite (N, 2) array")
        keep = np.concatenate([[True], np.linalg.norm(np.diff(pts, axis=0), axis=1) > 1e-9])
        pts = pts[keep]
        if len(pts) < 2:
            raise ValueError("a path needs at least two distinct points")
        seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        cum = np.concatenate([[0.0], np.cumsum(seg)])
        n = max(2, int(math.ceil(cum[-1] / STEP)) + 1)
        s = np.linspace(0.0, cum[-1], n)
        xy = np.stack([np.interp(s, cum, pts[:, 0]), np.interp(s, cum, pts[:, 1])], axis=1)
        if smoothing > 0 and n > 3:
            xy = _smooth(xy, smoothing / (s[1] - s[0]))
            seg = np.linalg.norm(np.diff(xy, axis=0), axis=1)
            s = np.concatenate([[0.0], np.cumsum(seg)])
        self.xy = xy
        self.s = s
        d = np.gradient(xy, s, axis=0)
        self.theta = np.arctan2(d[:, 1], d[:, 0])
        self.curvature = np.gradient(np.unwrap(self.theta), s)

    @property
    def length(self) -> float:
        return float(self.s[-1])

    def point_at(self, s: float) -> tuple[float, float, float]:
        """``(x, y, theta)`` at arc length ``s`` (clipped to the path)."""
        s = min(max(float(s), 0.0), self.length)
        th = np.unwrap(self.theta)
        return (float(np.interp(s, self.s, self.xy[:, 0])), float(np.interp(s, self.s, self.xy[:, 1])),
                float(wrap_angle(np.interp(s, self.s, th))))

    def project(self, xy, *, s_hint: float | None = None, window: float = 10.0) -> Projection:
        """The reference point of position ``xy`` (Li eq. 7).

        Parameters
        ----------
        xy : (2,) float
        s_hint : float, optional
            Arc length of the previous reference point. When given, only the part of the
            path from ``window / 4`` behind it to ``window`` ahead is searched, so that a path
            passing the same place twice (a loop) is followed in order. Without it, the
            earliest passage within :attr:`AMBIGUITY_M` of the closest is taken.
        window : float
            Metres searched ahead of ``s_hint``.
        """
        p = np.asarray(xy, np.float64)
        lo, hi = 0, len(self.s) - 1
        if s_hint is not None:
            lo = int(np.searchsorted(self.s, s_hint - window / 4, side="left"))
            hi = int(np.searchsorted(self.s, s_hint + window, side="right"))
            lo, hi = max(0, min(lo, len(self.s) - 2)), min(len(self.s) - 1, max(hi, lo + 1))
        a, b = self.xy[lo:hi], self.xy[lo + 1:hi + 1]
        ab = b - a
        t = np.clip(np.einsum("ij,ij->i", p - a, ab) / np.einsum("ij,ij->i", ab, ab), 0.0, 1.0)
        foot = a + t[:, None] * ab
        dist = np.sqrt(np.einsum("ij,ij->i", p - foot, p - foot))
        k = int(np.argmin(dist))
        if s_hint is None:
            # a path that passes the same place twice (a loop that ends where it began):
            # without a hint, the robot is where it passes first
            close = dist <= dist[k] + self.AMBIGUITY_M
            first = int(np.argmax(close))
            end = first + (int(np.argmin(close[first:])) if not close[first:].all()
                           else len(close) - first)
            k = first + int(np.argmin(dist[first:end]))
        i, tk = lo + k, float(t[k])
        s = float(self.s[i] + tk * (self.s[i + 1] - self.s[i]))
        th0, th1 = self.theta[i], self.theta[i] + wrap_angle(self.theta[i + 1] - self.theta[i])
        theta = float(wrap_angle(th0 + tk * (th1 - th0)))
        c = float(self.curvature[i] + tk * (self.curvature[i + 1] - self.curvature[i]))
        normal = np.array([-math.sin(theta), math.cos(theta)])
        d = float((p - foot[k]) @ normal)
        return Projection(s=s, x=float(foot[k, 0]), y=float(foot[k, 1]), theta=theta, d=d,
                          curvature=c)


def _smooth(xy: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian smoothing of a polyline that keeps its ends: the path is extended past each
    end by its point reflection there, so a straight end stays straight and in place."""
    m = min(len(xy) - 1, int(math.ceil(4 * sigma)))
    head = 2 * xy[0] - xy[m:0:-1]
    tail = 2 * xy[-1] - xy[-2:-m - 2:-1]
    out = gaussian_filter1d(np.vstack([head, xy, tail]), sigma, axis=0, mode="nearest")
    return out[m:m + len(xy)]
