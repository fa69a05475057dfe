"""Bringing a reconstruction onto the map's GPS: a robust, weighted similarity.

Structure from motion recovers the cameras up to a similarity (scale, rotation, shift). The
map's frame is east-north-up (:mod:`workers.core.geo`), and each map image's GPS tag says
where its camera is, horizontally to a few metres and vertically much worse: consumer GPS
altitudes are two to three times noisier than positions and drift during a flight (a nadir
survey seen drifting 317 -> 431 m). The similarity therefore weighs the misfit of each
camera's centre per axis (``sigma_h`` horizontally, ``sigma_v`` vertically), and adds what
every camera says of the vertical whatever the survey: cameras do not roll, so each
camera's x axis (the image's rows) lies level (``sigma_roll_deg``). A map image whose camera
the structure placed badly (the baseline's img_4204 on lewis-uav, 106 m off vertically) must
not pull the rest: candidates come from a RANSAC over three-camera samples
(Umeyama's closed form), and the final fit is a robust least-squares over all cameras.
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
    sigma_h, sigma_v : float
        GPS standard deviations (m) horizontally and vertically.
    sigma_roll_deg : float
        Standard deviation of a camera's roll.
    gate : float
        A camera is an inlier when its whitened misfit (the root of the squared horizontal
        and vertical misfits over their sigmas) is under this.
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

    def misfit(sim: Similarity) -> np.ndarray:
        d = sim.apply(centres) - target
        return np.sqrt((d[:, 0] ** 2 + d[:, 1] ** 2) / sigma_h ** 2 + d[:, 2] ** 2 / sv ** 2)

    best, best_count, best_cost = None, 0, np.inf
    for _ in range(iterations):
        sample = rng.choice(n, size=3, replace=False)
        sim = umeyama(centres[sample], target[sample])
        if sim is None:
            continue
        r = misfit(sim)
        inl = r < gate
        count, cost = int(inl.sum()), float(np.sum(np.minimum(r, gate) ** 2))
        if count > best_count or (count == best_count and cost < best_cost):
            best, best_count, best_cost = sim, count, cost
    if best is None or best_count < 3:
        return None
    inliers = misfit(best) < gate
    for _ in range(3):
        best = _refine(best, centres[inliers], right_axes[inliers], target[inliers],
                       sigma_h, sv[inliers], math.sin(math.radians(sigma_roll_deg)))
        now = misfit(best) < gate
        if now.sum() < 3 or np.array_equal(now, inliers):
            break
        inliers = now
    return best, misfit(best) < gate


def _refine(start: Similarity, centres: np.ndarray, right_axes: np.ndarray,
            target: np.ndarray, sigma_h: float, sigma_v: np.ndarray,
            roll_sigma: float) -> Similarity:
    """Weighted least squares over the inliers from ``start`` (rotation vector, log scale,
    shift), with the level right axes; a soft-L1 loss keeps a near-outlier from pulling."""
    x0 = np.concatenate([Rotation.from_matrix(start.rotation).as_rotvec(),
                         [math.log(start.scale)], start.shift])

    def unpack(x: np.ndarray) -> Similarity:
        return Similarity(math.exp(x[3]), Rotation.from_rotvec(x[:3]).as_matrix(), x[4:])

    def residuals(x: np.ndarray) -> np.ndarray:
        sim = unpack(x)
        d = sim.apply(centres) - target
        level = right_axes @ sim.rotation.T
        return np.concatenate([d[:, 0] / sigma_h, d[:, 1] / sigma_h, d[:, 2] / sigma_v,
                               level[:, 2] / roll_sigma])

    fit = least_squares(residuals, x0, loss="soft_l1", f_scale=2.0, method="trf")
    return unpack(fit.x)
