"""The 68 % horizontal accuracy radius against closed forms and a slow reference."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import erfinv

from vloc.workers.core.accuracy import horizontal_accuracy


def _reference(cov, p, n=4_000_000, seed=3) -> float:
    """The p-quantile of the distance of normal samples from their mean."""
    z = np.random.default_rng(seed).multivariate_normal([0.0, 0.0], cov, size=n)
    return float(np.quantile(np.hypot(z[:, 0], z[:, 1]), p))


@pytest.mark.parametrize("sigma", [0.1, 1.0, 13.0])
@pytest.mark.parametrize("p", [0.5, 0.68, 0.95])
def test_circular_error_has_the_rayleigh_radius(sigma, p):
    expected = sigma * math.sqrt(-2.0 * math.log(1.0 - p))
    assert horizontal_accuracy([sigma**2, 0.0, 0.0, sigma**2], p) == \
        pytest.approx(expected, rel=1e-9)


def test_a_line_has_the_normal_quantile():
    # all the error along one (rotated) axis: |Z| sigma < r with probability p
    s = 7.0
    c = np.array([[s * s / 2, s * s / 2], [s * s / 2, s * s / 2]])
    assert horizontal_accuracy(c) == pytest.approx(s * math.sqrt(2.0) * erfinv(0.68),
                                                   rel=1e-9)


@pytest.mark.parametrize("cov", [[[30.0, 12.0], [12.0, 10.0]], [[400.0, 0.0], [0.0, 4.0]],
                                 [[1.0, -0.9], [-0.9, 1.0]]])
def test_elliptic_error_matches_sampling(cov):
    assert horizontal_accuracy(cov) == pytest.approx(_reference(cov, 0.68), rel=3e-3)


def test_bounds_and_degenerate_input():
    c = [[30.0, 12.0], [12.0, 10.0]]
    lam = np.linalg.eigvalsh(c)
    r = horizontal_accuracy(c)
    # between the circles of the smaller and the larger axis
    k = math.sqrt(-2.0 * math.log(0.32))
    assert k * math.sqrt(lam[0]) < r < k * math.sqrt(lam[1])
    assert horizontal_accuracy([0.0, 0.0, 0.0, 0.0]) == 0.0
    assert math.isnan(horizontal_accuracy([math.nan, 0.0, 0.0, 1.0]))
    with pytest.raises(ValueError):
        horizontal_accuracy(c, 1.0)
