"""Li et al. eq. 8 against hand-computed values and its two special cases."""

import math

import numpy as np
import pytest

from vloc.workers.core.navigation import ControlConfig, Path, path_following_command, unicycle_step


def test_gains_follow_alpha_and_xi():
    c = ControlConfig(alpha=0.5)
    assert c.k2 == pytest.approx(0.25)
    assert c.k3 == pytest.approx(2 * 0.5 / math.sqrt(2))


def test_command_against_hand_computed_value():
    c = ControlConfig(alpha=1.0, v_max=0.5, w_max=10.0)
    d, th, curv = 0.2, 0.1, 0.05
    want = (-c.k3 * 0.5 * th - c.k2 * 0.5 * d * math.sin(th) / th
            + 0.5 * math.cos(th) * curv / (1 - curv * d))
    v, w = path_following_command(d, th, curv, c)
    assert v == 0.5
    assert w == pytest.approx(want, rel=1e-12)


def test_straight_line_case_is_two_terms():
    # c(s) = 0: omega is a heading term and a distance term only, both turning back
    c = ControlConfig(alpha=1.0, v_max=1.0, w_max=10.0)
    assert path_following_command(0.0, 0.0, 0.0, c) == (1.0, 0.0)
    assert path_following_command(0.5, 0.0, 0.0, c)[1] == pytest.approx(-0.5)
    assert path_following_command(0.0, 0.2, 0.0, c)[1] == pytest.approx(-c.k3 * 0.2)


def test_circle_case_is_constant_omega():
    # on a circle of radius 4 with no error, omega = v c: the constant turn of the circle
    c = ControlConfig(v_max=0.8, w_max=10.0)
    assert path_following_command(0.0, 0.0, 0.25, c) == pytest.approx((0.8, 0.2))


def test_saturation_reduces_speed():
    c = ControlConfig(alpha=2.0, v_max=1.0, w_max=0.5)
    v, w = path_following_command(2.0, 0.0, 0.0, c)
    raw = c.k2 * 1.0 * 2.0
    assert w == -0.5
    assert v == pytest.approx(1.0 * 0.5 / raw)


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), True])
def test_config_rejects_bad_gain(bad):
    with pytest.raises(ValueError, match="alpha"):
        ControlConfig(alpha=bad)


def _drive(path, pose, config, steps, dt=0.1):
    ds, s = [], 0.0
    for _ in range(steps):
        p = path.project(pose[:2], s_hint=s)
        s = p.s
        th = math.atan2(math.sin(pose[2] - p.theta), math.cos(pose[2] - p.theta))
        v, w = path_following_command(p.d, th, p.curvature, config)
        pose = unicycle_step(pose, v, w, dt)
        ds.append(p.d)
    return pose, np.array(ds)


def test_closed_loop_converges_to_straight_line():
    path = Path(np.array([[0.0, 0.0], [60.0, 0.0]]), smoothing=0)
    _, d = _drive(path, np.array([0.0, 1.0, math.radians(20)]), ControlConfig(alpha=1.0), 600)
    assert abs(d[0]) == pytest.approx(1.0)
    assert np.abs(d[-100:]).max() < 0.01
    # xi = 1/sqrt(2): a small overshoot, not an oscillation
    assert d.min() > -0.3


def test_closed_loop_holds_a_circle():
    t = np.linspace(0, 1.9 * math.pi, 2000)
    path = Path(np.c_[5 * np.cos(t), 5 * np.sin(t)], smoothing=0)
    _, d = _drive(path, np.array([5.5, 0.0, math.pi / 2]), ControlConfig(alpha=1.0, w_max=2.0), 400)
    assert np.abs(d[-100:]).max() < 0.02
