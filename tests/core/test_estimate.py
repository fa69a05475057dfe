"""What a client is told of an estimate, decided in one place (:func:`judge`)."""

from __future__ import annotations

import math

import pytest

from vloc.workers.core.estimate import Status, judge

RADIUS_PER_SIGMA = math.sqrt(-2.0 * math.log(1.0 - 0.68))
"""The 68 % circle of a circular normal error, in standard deviations."""


def _cov(accuracy_m: float) -> tuple[float, float, float, float]:
    """A circular covariance whose 68 % circle has the radius ``accuracy_m``."""
    s2 = (accuracy_m / RADIUS_PER_SIGMA) ** 2
    return (s2, 0.0, 0.0, s2)


@pytest.mark.parametrize(("core", "accuracy", "before", "expected"), [
    ("tracking", 5.0, False, ("tracking", True)),
    ("tracking", 50.0, False, ("initialising", False)),   # not yet converged
    ("tracking", 50.0, True, ("tracking", False)),        # converged earlier, spread now
    ("tracking", 25.01, False, ("initialising", False)),  # just outside the bound
    ("initialising", 5.0, False, ("initialising", False)),
    ("lost", 5.0, True, ("lost", False)),
])
def test_status_converged_and_accuracy(core, accuracy, before, expected):
    verdict = judge(Status(core), _cov(accuracy), bound_m=25.0, converged_before=before)
    assert (str(verdict.status), verdict.converged) == expected
    assert verdict.horizontal_accuracy_m == pytest.approx(accuracy, rel=1e-9)
    assert isinstance(verdict.horizontal_accuracy_m, float)
