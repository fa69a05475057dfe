"""Bringing a reconstruction onto the map's GPS: a robust, weighted similarity.

Structure from motion recovers the cameras up to a similarity (scale, rotation, shift). The
map's frame is east-north-up (:mod:`workers.core.geo`), and each map image's GPS tag says
where its camera is, horizontally to a few metres and vertically much worse: consumer GPS
altitudes are two to three times noisier than positions and drift during a flight (a nadir
survey seen drifting 317 -> 431 m). The similarity therefore

- weighs each camera's misfit per axis (``sigma_h`` horizontally, ``sigma_v`` vertically);
- where the capture times are known, lets the GPS altitudes drift linearly in time. A drift
  is a function of time and a tilt of the model one of position: over a lawnmower survey,
  whose legs run back and forth, time and position part, and a drift no longer tilts the
  model (100 m of drift tilted a survey's model 30 degrees about its flight lines);
- adds what every camera says of the vertical whatever the survey: cameras do not roll, so
  each camera's x axis (the image's rows) lies level (``sigma_roll_deg``).

A map image whose camera the structure placed badly (the COLMAP baseline's img_4204 on
lewis-uav, 106 m off vertically) must not pull the rest: candidates come from a RANSAC over
camera samples judged by their horizontal misfit, and the final fit is a robust least
squares over the inliers. Cameras along one line (a straight street, a single flight line)
leave the rotation about that line to the cameras' own axes: level rows, and the view or the
image's downward direction pointing down rather than up (an upside-down model keeps every
row level too).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation


@dataclass(frozen=True)
class Similarity:
    """``x -> scale * rotation @ x + shift``."""

    scale: float
    rotation: np.ndarray  # (3, 3)
    shift: np.ndarray  # (3,)

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Transform (n, 3) points."""
        return self.scale * np.asarray(points, np.float64) @ self.rotation.T + self.shift

    def apply_to_rotations(self, rotations: np.ndarray) -> np.ndarray:
        """World -> camera rotations (n, 3, 3) expressed in the transformed world."""
        return np.asarray(rotations, np.float64) @ self.rotation.T


def umeyama(src: np.ndarray, dst: np.ndarray) -> Similarity | None:
    """Least-squares similarity taking ``src`` (n, 3) onto ``dst`` (n, 3) (Umeyama 1991);
    None for fewer than three points or a degenerate (collinear) set."""
    src = np.asarray(src, np.float64)
    dst = np.asarray(dst, np.float64)
    if len(src) < 3:
        return None
    ms, md = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - ms, dst - md
    var = float(np.mean(np.sum(a ** 2, axis=1)))
    if var <= 1e-12:
        return None
    U, d, Vt = np.linalg.svd(b.T @ a / len(src))
    if d[1] <= 1e-9 * d[0]:
        return None
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    scale = float(np.trace(np.diag(d) @ S) / var)
    return Similarity(scale, R, md - scale * R @ ms)


def align_to_gps(centres: np.ndarray, right_axes: np.ndarray, gps: np.ndarray, *,
                 axes: np.ndarray | None = None, times: np.ndarray | None = None,
                 sigma_h: float = 5.0, sigma_v: float = 15.0, sigma_roll_deg: float = 5.0,
                 gate: float = 3.0, iterations: int = 300,
                 rng: np.random.Generator) -> tuple[Similarity, np.ndarray] | None:
    """The similarity taking a reconstruction's camera centres onto their GPS positions.

    Parameters
    ----------
    centres : (n, 3) float ndarray
        Camera centres in the reconstruction's frame.
    right_axes : (n, 3) float ndarray
        Each camera's x axis in the reconstruction's frame (row 0 of its world -> camera
        rotation): level in the map's frame for a camera that does not roll.
    gps : (n, 3) float ndarray
        East, north, altitude of each camera's GPS tag; a NaN altitude leaves the vertical
        to the others.
    axes : (n, 3, 3) float ndarray, optional
        The cameras' world -> camera rotations, for cameras along one line (the rotation
        about it); by default only ``right_axes`` speak of it.
    times : (n,) float ndarray, optional
        Capture times (s, NaN unknown): the altitudes may then drift linearly in time.
    sigma_h, sigma_v : float
        GPS standard deviations (m) horizontally and vertically.
    sigma_roll_deg : float
        Standard deviation of a camera's roll.
    gate : float
        A camera is an inlier when its whitened misfit (horizontal and vertical, the
        altitudes' drift taken out) is under this.
    rng : numpy.random.Generator
        Draws the RANSAC samples.

    Returns
    -------
    (Similarity, (n,) bool inliers) or None
        None for fewer than three cameras or no consistent sample.
    """
    centres = np.asarray(centres, np.float64)
    right_axes = np.asarray(right_axes, np.float64)
    gps = np.asarray(gps, np.float64)
    n = len(centres)
    if n < 3:
        return None
    has_alt = np.isfinite(gps[:, 2])
    target = gps.copy()
    # unknown altitudes: the median of the others, with no weight
    target[~has_alt, 2] = np.median(gps[has_alt, 2]) if has_alt.any() else 0.0
    sv = np.where(has_alt, sigma_v, 1e6)
    t = _drift_times(times, has_alt)
    roll = math.sin(math.radians(sigma_roll_deg))

    def horizontal(sim: Similarity) -> np.ndarray:
        d = sim.apply(centres)[:, :2] - target[:, :2]
        return np.sqrt(np.sum(d ** 2, axis=1)) / sigma_h

    line = _along_a_line(target, has_alt, sigma_h)
    best, best_count, best_cost = None, 0, np.inf
    for _ in range(iterations):
        if line:
            i, j = rng.choice(n, size=2, replace=False)
            sim = _on_a_line(centres[[i, j]], target[[i, j]], right_axes, axes)
        else:
            sim = umeyama(centres[sample := rng.choice(n, size=3, replace=False)],
                          target[sample])
        if sim is None:
            continue
        r = horizontal(sim)
        inl = r < gate
        count, cost = int(inl.sum()), float(np.sum(np.minimum(r, gate) ** 2))
        if count > best_count or (count == best_count and cost < best_cost):
            best, best_count, best_cost = sim, count, cost
    if best is None or best_count < 3:
        return None
    inliers = horizontal(best) < gate
    drift = 0.0
    for _ in range(4):
        best, drift = _refine(best, centres[inliers], right_axes[inliers], target[inliers],
                              sigma_h, sv[inliers], None if t is None else t[inliers], roll)
        now = _misfit(best, drift, centres, target, sigma_h, sv, t) < gate
        if now.sum() < 3 or np.array_equal(now, inliers):
            break
        inliers = now
    return best, _misfit(best, drift, centres, target, sigma_h, sv, t) < gate


def _drift_times(times: np.ndarray | None, has_alt: np.ndarray) -> np.ndarray | None:
    """Capture times (centred, s) where enough cameras with an altitude have one, so that a
    drift can be told apart; None otherwise."""
    if times is None:
        return None
    t = np.asarray(times, np.float64)
    known = np.isfinite(t) & has_alt
    if known.sum() < 6 or np.ptp(t[known]) <= 0:
        return None
    return np.where(np.isfinite(t), t - np.median(t[known]), 0.0)


def _misfit(sim: Similarity, drift: float, centres: np.ndarray, target: np.ndarray,
            sigma_h: float, sv: np.ndarray, t: np.ndarray | None) -> np.ndarray:
    """Each camera's whitened misfit, the altitudes' drift taken out."""
    d = sim.apply(centres) - target
    if t is not None:
        d[:, 2] += drift * t
    return np.sqrt((d[:, 0] ** 2 + d[:, 1] ** 2) / sigma_h ** 2 + d[:, 2] ** 2 / sv ** 2)


def _along_a_line(target: np.ndarray, has_alt: np.ndarray, sigma_h: float) -> bool:
    """Whether the cameras lie along one line: their spread across it (RMS, horizontally and,
    where known, vertically) within twice the GPS noise."""
    xyz = target.copy()
    if not has_alt.any():
        xyz[:, 2] = 0.0
    sv = np.linalg.svd(xyz - xyz.mean(axis=0), compute_uv=False)
    return bool(sv[1] / math.sqrt(len(xyz)) < 2.0 * sigma_h)


def _on_a_line(src: np.ndarray, dst: np.ndarray, right_axes: np.ndarray,
               axes: np.ndarray | None) -> Similarity | None:
    """The similarity taking two cameras onto their tags, turned about the line through them
    so that the cameras' rows lie level and they look, or their images point, down."""
    ds, dt = src[1] - src[0], dst[1] - dst[0]
    ls, lt = float(np.linalg.norm(ds)), float(np.linalg.norm(dt))
    if ls <= 1e-9 or lt <= 1e-9:
        return None
    u_s, u = ds / ls, dt / lt
    R0 = _rotation_between(u_s, u)
    angles = np.radians(np.arange(0.0, 360.0, 0.5))
    cos, sin = np.cos(angles)[:, None], np.sin(angles)[:, None]

    def height(vectors: np.ndarray) -> np.ndarray:
        """(angles, n) vertical part of ``vectors`` (n, 3) turned by R0 and then by each
        angle about ``u`` (Rodrigues: w cos + (u x w) sin + u (u.w)(1 - cos))."""
        w = vectors @ R0.T
        along = w @ u
        return (w[:, 2] - u[2] * along) * cos + np.cross(u, w)[:, 2] * sin + u[2] * along

    cost = np.mean(height(right_axes) ** 2, axis=1) / math.sin(math.radians(5.0)) ** 2
    if axes is not None:
        # the image's down (y) or the view (z), whichever is steeper, should point down
        cost -= np.mean(np.maximum(-height(axes[:, 1, :]), -height(axes[:, 2, :])), axis=1)
    R = Rotation.from_rotvec(angles[int(np.argmin(cost))] * u).as_matrix() @ R0
    scale = lt / ls
    return Similarity(scale, R, dst[0] - scale * R @ src[0])


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """A rotation taking unit vector ``a`` to unit vector ``b``."""
    v, c = np.cross(a, b), float(np.dot(a, b))
    if np.linalg.norm(v) < 1e-12:
        if c > 0:
            return np.eye(3)
        # opposite: half a turn about any axis across a
        perp = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
        return Rotation.from_rotvec(math.pi * perp / np.linalg.norm(perp)).as_matrix()
    angle = math.atan2(float(np.linalg.norm(v)), c)
    return Rotation.from_rotvec(angle * v / np.linalg.norm(v)).as_matrix()


def _refine(start: Similarity, centres: np.ndarray, right_axes: np.ndarray,
            target: np.ndarray, sigma_h: float, sigma_v: np.ndarray,
            t: np.ndarray | None, roll_sigma: float) -> tuple[Similarity, float]:
    """Weighted least squares over the inliers from ``start`` (rotation vector, log scale,
    shift, and with ``t`` the altitudes' drift in m/s), with the level right axes; a
    soft-L1 loss keeps a near-outlier from pulling."""
    x0 = np.concatenate([Rotation.from_matrix(start.rotation).as_rotvec(),
                         [math.log(start.scale)], start.shift, [0.0] if t is not None else []])

    def unpack(x: np.ndarray) -> Similarity:
        return Similarity(math.exp(x[3]), Rotation.from_rotvec(x[:3]).as_matrix(), x[4:7])

    def residuals(x: np.ndarray) -> np.ndarray:
        sim = unpack(x)
        d = sim.apply(centres) - target
        if t is not None:
            d[:, 2] += x[7] * t
        level = right_axes @ sim.rotation.T
        return np.concatenate([d[:, 0] / sigma_h, d[:, 1] / sigma_h, d[:, 2] / sigma_v,
                               level[:, 2] / roll_sigma])

    fit = least_squares(residuals, x0, loss="soft_l1", f_scale=2.0, method="trf")
    return unpack(fit.x), float(fit.x[7]) if t is not None else 0.0
