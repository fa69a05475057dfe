"""Path following in closed loop on the unicycle: convergence, arrival, checkpointing."""

import math

import numpy as np
import pytest

from vloc.workers.core.navigation import (
    ActuationNoise,
    ControlConfig,
    FollowerConfig,
    Path,
    PathFollower,
    unicycle_step,
)


def _path():
    t = np.linspace(0, 1.2 * math.pi, 600)
    return Path(np.c_[np.r_[np.linspace(-15, 0, 100), 12 * np.sin(t)],
                      np.r_[np.zeros(100), 12 - 12 * np.cos(t)]], smoothing=1.0)


def _run(follower, pose, rng, steps, sigma=0.25):
    noise = ActuationNoise()
    true_d, out = [], []
    for _ in range(steps):
        z = pose[:2] + rng.normal(0, sigma, 2)
        h = pose[2] + rng.normal(0, math.radians(5))
        st = follower.step(z, np.eye(2) * sigma ** 2, heading=h)
        out.append(st)
        if st.arrived:
            break
        v, w = noise.apply(*st.command, rng)
        for _ in range(5):
            pose = unicycle_step(pose, v, w, 0.2)
        true_d.append(follower.path.project(pose[:2], s_hint=st.progress).d)
    return pose, np.array(true_d), out


def test_converges_from_one_metre_and_twenty_degrees_off_and_arrives():
    path = _path()
    rng = np.random.default_rng(0)
    follower = PathFollower(path, [0.0, 15.0], FollowerConfig(control=ControlConfig(alpha=0.7)))
    pose = np.array([-14.0, -1.0, math.radians(20)])
    _, d, steps = _run(follower, pose, rng, 200)
    travelled = np.cumsum([s.command[0] for s in steps])
    after_5m = np.searchsorted(travelled, 5.0)
    assert abs(d[0]) > 0.6
    assert np.abs(d[after_5m:]).max() < 0.45
    assert np.abs(d[after_5m:]).mean() < 0.15
    assert steps[-1].arrived and steps[-1].command == (0.0, 0.0)
    assert steps[-1].progress == pytest.approx(path.length, abs=0.6)
    assert [s.node for s in steps][0] == 0 and steps[-1].node == 1


def test_the_filter_moves_by_the_command_just_driven():
    """Between two frames the robot drives the command of the first; the filter's heading
    at the second has turned by that command's omega, not by the velocities it had before
    (which left the heading one sharp correction behind)."""
    path = _path()
    follower = PathFollower(path, [0.0])
    for k in range(4):                       # driving straight along the path, on it
        st = follower.step((-15 + 0.6 * k, 0.0), np.eye(2) * 0.01, heading=0.0)
    follower.command = (0.6, 0.5)            # a sharp turn is commanded...
    st = follower.step(None, None)           # ...and driven for a second, with no fix
    assert st.state[4] == pytest.approx(0.5, abs=0.02)
    assert st.state[2] == pytest.approx(0.5, abs=0.03)
    # the position moved along the arc's chord (midpoint rule), turned left
    assert st.state[1] == pytest.approx(0.6 * math.sin(0.25), abs=0.03)


def test_outlier_fix_is_gated():
    path = _path()
    follower = PathFollower(path, [0.0])
    for k in range(5):
        follower.step((-15 + 0.6 * k, 0.0), np.eye(2) * 0.04, heading=0.0)
    st = follower.step((10.0, 20.0), np.eye(2) * 0.04, heading=0.0)
    assert not st.fused
    assert st.state[0] < -10


def test_fixes_that_keep_disagreeing_start_the_filter_again():
    """One fix outside the gate is a false recognition; REACQUIRE of them in a row mean the
    filter is the one that is wrong, and it starts again from the last fix, keeping its
    velocities. A fix inside the gate in between resets the count."""
    from vloc.workers.core.navigation.follower import REACQUIRE

    path = _path()
    follower = PathFollower(path, [0.0])
    for k in range(5):
        follower.step((-15 + 0.6 * k, 0.0), np.eye(2) * 0.01, heading=0.0)
    for k in range(REACQUIRE - 1):
        st = follower.step((-12.0 + 0.6 * k, 2.0), np.eye(2) * 0.01, heading=0.3)
        assert not st.fused and abs(st.state[1]) < 0.5
    st = follower.step((-10.5, 0.0), np.eye(2) * 0.01, heading=0.0)   # agrees: count reset
    assert st.fused
    for k in range(REACQUIRE):
        st = follower.step((-10.0 + 0.6 * k, 2.0), np.eye(2) * 0.01, heading=0.3)
    assert st.fused
    assert st.state[:3] == pytest.approx((-10.0 + 0.6 * (REACQUIRE - 1), 2.0, 0.3))
    assert st.state[3] > 0.1           # still driving: the velocities were kept
    # the new estimate is the filter's from now on: fixes beside it are fused
    assert follower.step((-8.0, 2.0), np.eye(2) * 0.01, heading=0.3).fused


def test_checkpoint_restores_the_same_commands():
    path = _path()
    a = PathFollower(path, [0.0])
    for k in range(6):
        a.step((-15 + 0.6 * k, 0.1), np.eye(2) * 0.04, captured_at=float(k))
    a.step((5.0, 9.0), np.eye(2) * 0.01)   # rejected: the count travels with the state
    assert a.rejected == 1
    b = PathFollower(path, [0.0])
    b.set_state(a.get_state())
    assert b.rejected == 1
    sa = a.step((-11.3, 0.2), np.eye(2) * 0.04, captured_at=6.0)
    sb = b.step((-11.3, 0.2), np.eye(2) * 0.04, captured_at=6.0)
    assert sa == sb


def test_config_from_params_and_unknown_keys():
    cfg = FollowerConfig.from_params({"alpha": 1.5, "v_max": 0.4, "arrive_tolerance": 1.0})
    assert cfg.control.alpha == 1.5 and cfg.arrive_tolerance == 1.0
    assert FollowerConfig.from_params(cfg.to_params()) == cfg
    with pytest.raises(ValueError, match="bogus"):
        FollowerConfig.from_params({"bogus": 1})
