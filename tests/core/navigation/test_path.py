"""The reference point of Li eq. 7, signed distance, heading and curvature."""

import math

import numpy as np
import pytest

from vloc.workers.core.navigation import Path


def test_projection_onto_a_line_by_hand():
    path = Path(np.array([[0.0, 0.0], [10.0, 0.0]]), smoothing=0)
    p = path.project((3.2, 0.7))
    assert (p.s, p.x, p.y) == pytest.approx((3.2, 3.2, 0.0))
    assert p.theta == pytest.approx(0.0)
    assert p.d == pytest.approx(0.7)           # left of travel is positive
    assert path.project((3.2, -0.4)).d == pytest.approx(-0.4)
    assert p.curvature == pytest.approx(0.0)


def test_circle_has_curvature_one_over_radius():
    t = np.linspace(0, 1.5 * math.pi, 3000)
    path = Path(np.c_[4 * np.cos(t), 4 * np.sin(t)], smoothing=0.5)
    p = path.project((0.0, 5.0))                # outside the circle, at its top
    assert p.curvature == pytest.approx(0.25, rel=0.02)
    # outside of a left turn is to the right; smoothing pulls the circle in by
    # R (1 - exp(-sigma^2 / 2 R^2)), 3 cm here
    assert p.d == pytest.approx(-1.0 - 4 * (1 - math.exp(-0.25 / 32)), abs=0.005)
    assert math.cos(p.theta) == pytest.approx(-1.0, abs=1e-4)
    assert path.length == pytest.approx(4 * 1.5 * math.pi, rel=0.01)


def test_hint_keeps_the_reference_on_the_current_pass_of_a_loop():
    # out along y = 0 and back along y = 0.5: the same place twice
    pts = np.array([[0, 0], [20, 0], [20, 0.5], [0, 0.5]], float)
    path = Path(pts, smoothing=0)
    # without a hint the first passage wins while it is within a metre of the closest
    assert path.project((5.0, 0.4)).s == pytest.approx(5.0)
    assert path.project((5.0, 0.4), s_hint=30.0).s == pytest.approx(35.5)
    assert path.project((5.0, 0.3), s_hint=4.0).s == pytest.approx(5.0)
    wide = Path(np.array([[0, 0], [20, 0], [20, 3], [0, 3]], float), smoothing=0)
    assert wide.project((5.0, 2.8)).s == pytest.approx(38.0)      # clearly the way back


def test_point_at_and_bad_points():
    path = Path(np.array([[0.0, 0.0], [0.0, 4.0]]), smoothing=0)
    assert path.point_at(1.0) == pytest.approx((0.0, 1.0, math.pi / 2))
    assert path.point_at(99.0)[1] == pytest.approx(4.0)
    with pytest.raises(ValueError):
        Path(np.array([[0.0, 0.0], [0.0, 0.0]]))
    with pytest.raises(ValueError):
        Path(np.array([[0.0, float("nan")], [1.0, 0.0]]))
