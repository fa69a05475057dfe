"""Duckett et al.'s relaxation (Li eqs. 1-3): known answers and the fixed point by hand."""

import math

import numpy as np
import pytest

from vloc.workers.core.navigation import Arc, relax
from vloc.workers.core.navigation.relaxation import predict, relative_pose


def _square(side=10.0, per_side=4):
    """Poses round a square, anticlockwise, heading along the direction of travel."""
    poses = []
    for k in range(4):
        th = k * math.pi / 2
        c, s = math.cos(th), math.sin(th)
        corner = [(0, 0), (side, 0), (side, side), (0, side)][k]
        for j in range(per_side):
            t = side * j / per_side
            poses.append((corner[0] + c * t, corner[1] + s * t, th))
    return np.array(poses)


def _chain_arcs(poses, var=0.1):
    return [Arc(k, k + 1, *relative_pose(poses[k], poses[k + 1]), variance=var)
            for k in range(len(poses) - 1)]


def test_relative_pose_and_predict_invert_each_other():
    a, b = (1.0, 2.0, 0.5), (3.0, -1.0, 2.5)
    arc = Arc(0, 1, *relative_pose(a, b), variance=1.0)
    assert np.allclose(predict(a, arc, True), (b[0], b[1], b[2]))
    back = predict(b, arc, False)
    assert np.allclose(back[:2], a[:2])
    assert math.cos(back[2] - a[2]) == pytest.approx(1.0)


def test_consistent_arcs_recover_true_poses_from_a_scrambled_start():
    truth = _square()
    arcs = _chain_arcs(truth) + [Arc(len(truth) - 1, 0, *relative_pose(truth[-1], truth[0]), 0.1)]
    start = truth + np.random.default_rng(0).normal(0, [0.8, 0.8, 0.1], truth.shape)
    start[0] = truth[0]
    out = relax(start, arcs, tol=1e-9)
    assert out.converged
    assert np.abs(out.poses[:, :2] - truth[:, :2]).max() < 1e-4


def test_loop_closure_spreads_the_drift_and_shrinks_the_error():
    truth = _square(per_side=6)
    # odometry that turns 2 degrees too far at every step: the loop does not close
    odo_arcs = []
    for arc in _chain_arcs(truth):
        odo_arcs.append(Arc(arc.a, arc.b, arc.dx * 1.02, arc.dy, arc.dtheta + math.radians(2), 0.1))
    odo = [truth[0]]
    for arc in odo_arcs:
        odo.append(predict(odo[-1], arc, True))
    odo = np.array(odo)
    before = np.hypot(*(odo[:, :2] - truth[:, :2]).T)
    loop = Arc(len(truth) - 1, 0, *relative_pose(truth[-1], truth[0]), 0.01)
    out = relax(odo, odo_arcs + [loop], node_variances=False)
    after = np.hypot(*(out.poses[:, :2] - truth[:, :2]).T)
    assert before.max() > 3.0
    assert after.max() < 0.2 * before.max()
    assert after.mean() < 0.2 * before.mean()
    # node 0 is the reference and never moves
    assert np.array_equal(out.poses[0], odo[0])
    paper = relax(odo, odo_arcs + [loop])
    assert np.hypot(*(paper.poses[:, :2] - truth[:, :2]).T).mean() < 0.8 * before.mean()


def test_result_is_the_fixed_point_of_eqs_1_to_3():
    """Apply eqs. 1-3 once more by hand to every node: nothing should move."""
    truth = _square(per_side=3)
    arcs = [Arc(a.a, a.b, a.dx + 0.3, a.dy - 0.1, a.dtheta + 0.05, 0.1 + 0.05 * a.a)
            for a in _chain_arcs(truth)]
    arcs.append(Arc(0, len(truth) - 1, *relative_pose(truth[0], truth[-1]), 0.02))
    out = relax(truth, arcs, tol=1e-10, max_sweeps=20000)
    assert out.converged
    p, var = out.poses, out.variances
    for i in range(1, len(p)):
        est, w = [], []
        for arc in arcs:
            if arc.b == i:
                est.append(predict(p[arc.a], arc, True))
                w.append(1.0 / (var[arc.a] + arc.variance))
            elif arc.a == i:
                # x_a = x_b - R(theta_a) (dx, dy); the heading as eq. 1 predicts it
                c, s = math.cos(p[i, 2]), math.sin(p[i, 2])
                est.append((p[arc.b, 0] - (c * arc.dx - s * arc.dy),
                            p[arc.b, 1] - (s * arc.dx + c * arc.dy),
                            p[arc.b, 2] - arc.dtheta))
                w.append(1.0 / (var[arc.b] + arc.variance))
        est, w = np.array(est), np.array(w)
        n_i = len(w)
        omega_i = n_i / w.sum()                                        # eq. 2
        x = np.sum(est[:, 0] * omega_i * w) / n_i                      # eq. 3
        y = np.sum(est[:, 1] * omega_i * w) / n_i
        th = math.atan2(np.sum(np.sin(est[:, 2]) * w), np.sum(np.cos(est[:, 2]) * w))
        assert (x, y) == pytest.approx(tuple(p[i, :2]), abs=1e-6)
        assert math.cos(th - p[i, 2]) == pytest.approx(1.0, abs=1e-9)
        assert omega_i == pytest.approx(var[i], rel=1e-6)


def test_bad_arcs_are_refused():
    with pytest.raises(ValueError, match="distinct"):
        relax(np.zeros((2, 3)), [Arc(0, 0, 1, 0, 0, 1.0)])
    with pytest.raises(ValueError, match="positive variance"):
        relax(np.zeros((2, 3)), [Arc(0, 1, 1, 0, 0, 0.0)])


def test_arc_weights_undo_a_heading_bias_round_a_loop():
    """A circle driven with odometry that turns too far at every step, closed by one exact
    loop arc: weighted by the arcs, relaxation is the least-squares answer and puts every
    node back; eq. 1's node variances leave the headings bent."""
    n, radius = 60, 30.0
    t = np.linspace(0, 2 * math.pi, n, endpoint=False)
    truth = np.c_[radius * np.cos(t), radius * np.sin(t), t + math.pi / 2]
    arcs = [Arc(k, k + 1, *(np.array(relative_pose(truth[k], truth[k + 1]))
                            + [0, 0, math.radians(0.3)]), 0.03) for k in range(n - 1)]
    odo = [truth[0]]
    for arc in arcs:
        odo.append(predict(odo[-1], arc, True))
    loop = Arc(0, n - 1, *relative_pose(truth[0], truth[-1]), 0.01)
    before = np.hypot(*(np.array(odo)[:, :2] - truth[:, :2]).T).mean()
    arc_w = relax(np.array(odo), arcs + [loop], node_variances=False, tol=1e-7, max_sweeps=50000)
    node_w = relax(np.array(odo), arcs + [loop], node_variances=True, tol=1e-7, max_sweeps=50000)
    assert arc_w.converged and node_w.converged
    assert before > 4.0
    assert np.hypot(*(arc_w.poses[:, :2] - truth[:, :2]).T).max() < 0.15
    assert np.hypot(*(node_w.poses[:, :2] - truth[:, :2]).T).mean() > 0.5
