"""One horizontal accuracy figure from a 2-D position covariance.

Positioning APIs report accuracy as the radius of the circle, centred on the estimate, that
holds the true position with a stated probability (68 % by convention, the "one sigma" of a
phone's location fix). For a bivariate normal error with covariance ``C`` the squared
distance from the centre is ``l1 Z1^2 + l2 Z2^2`` (``l1 >= l2`` the eigenvalues of ``C``,
``Z`` standard normal), so the radius solves

    P(r) = integral over |z| < r / sqrt(l1) of phi(z) erf(sqrt((r^2 - l1 z^2) / (2 l2))) dz = p

which is exact; only the integral is evaluated numerically (Gauss-Legendre after a change of
variable that makes the integrand smooth) and the root found by Brent's method between the circles of the two axes. For a circular error (``l1 == l2 == s^2``)
it reduces to ``r = s sqrt(-2 ln(1 - p))``, 1.5096 s at 68 %.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import brentq
from scipy.special import erf

#: Probability of the horizontal accuracy circle.
CONFIDENCE = 0.68

_NODES, _WEIGHTS = np.polynomial.legendre.leggauss(48)


def horizontal_accuracy(cov, p: float = CONFIDENCE) -> float:
    """Radius (metres) of the circle about the estimate holding the position with
    probability ``p``.

    Parameters
    ----------
    cov : (2, 2) array_like or 4 floats
        Position covariance (row-major when flat), metres squared; symmetrised here.
    p : float
        Probability, in (0, 1).

    Returns
    -------
    float
        The radius; 0 for a zero covariance, NaN when ``cov`` is not finite.
    """
    if not 0.0 < p < 1.0:
        raise ValueError("p must be in (0, 1)")
    c = np.asarray(cov, np.float64).reshape(2, 2)
    if not np.all(np.isfinite(c)):
        return math.nan
    lam = np.clip(np.linalg.eigvalsh((c + c.T) / 2.0), 0.0, None)
    l2, l1 = float(lam[0]), float(lam[1])
    if l1 == 0.0:
        return 0.0
    if l2 <= 1e-12 * l1:
        # a line: |Z1| sqrt(l1) < r with probability p
        from scipy.special import erfinv
        return float(math.sqrt(2.0 * l1) * erfinv(p))
    # The root lies between the circles of the smaller and the larger axis.
    k = math.sqrt(-2.0 * math.log1p(-p))
    lo, hi = k * math.sqrt(l2), k * math.sqrt(l1)
    if hi - lo <= 1e-12 * hi:
        return hi
    return float(brentq(lambda r: _within(r, l1, l2) - p, lo, hi, xtol=1e-12 * hi,
                        rtol=1e-12))


def _within(r: float, l1: float, l2: float) -> float:
    """P(l1 Z1^2 + l2 Z2^2 < r^2), by Gauss-Legendre after z1 = (r / sqrt(l1)) sin t, which
    removes the square-root end points: the integrand becomes smooth in t."""
    a = r / math.sqrt(l1)
    t = 0.5 * math.pi * _NODES
    z = a * np.sin(t)
    phi = np.exp(-0.5 * z * z) / math.sqrt(2.0 * math.pi)
    inner = erf(r * np.cos(t) / math.sqrt(2.0 * l2))
    return float(0.5 * math.pi * a * np.sum(_WEIGHTS * phi * inner * np.cos(t)))
