"""Route maps: partitioning, loop closure, relaxation and alignment on a synthetic taught loop."""

import math

import numpy as np
import pytest

from vloc.workers.core.navigation import RouteParams, build_route
from vloc.workers.core.navigation.routemap import partition
from vloc.workers.core.navigation.unicycle import wrap_angle


def _taught_loop(rng, drift_deg_per_m=0.4, spacing=0.6):
    """A rectangle 30 x 16 m driven once and 6 m further, true poses and drifting odometry."""
    corners = np.array([[0, 0], [30, 0], [30, 16], [0, 16], [0, 0], [6, 0]], float)
    seg = np.diff(corners, axis=0)
    lengths = np.hypot(*seg.T)
    s = np.arange(0, lengths.sum(), spacing)
    cum = np.r_[0, np.cumsum(lengths)]
    xy = np.stack([np.interp(s, cum, corners[:, 0]), np.interp(s, cum, corners[:, 1])], axis=1)
    heading = np.arctan2(*np.gradient(xy, axis=0)[:, ::-1].T)
    truth = np.c_[xy, heading]
    odo = [truth[0].copy()]
    for k in range(1, len(truth)):
        d = float(np.hypot(*(truth[k, :2] - truth[k - 1, :2])))
        dth = wrap_angle(truth[k, 2] - truth[k - 1, 2]) + math.radians(drift_deg_per_m) * d
        th = odo[-1][2] + dth
        step = d * (1.0 + 0.01 * rng.standard_normal())
        odo.append(np.array([odo[-1][0] + step * math.cos(th), odo[-1][1] + step * math.sin(th), th]))
    return truth, np.array(odo)


def _appearance(truth):
    """Hue-like signatures that change smoothly with the place."""
    centres = np.linspace(0, 30, 8)
    return np.exp(-((truth[:, :1] - centres) ** 2 + (truth[:, 1:2] - 8) ** 2 / 4) / 60.0) * 0.05


def _verify(truth):
    def verify(image, candidates):
        # a forward camera sees the same view only from about the same pose
        gap = np.hypot(*(truth[candidates, :2] - truth[image, :2]).T)
        turn = np.abs(np.angle(np.exp(1j * (truth[candidates, 2] - truth[image, 2]))))
        return np.where((gap < 1.0) & (turn < 0.3), 0.4 - 0.1 * gap, 0.02)
    return verify


def test_partition_closes_nodes_on_distance_features_and_appearance():
    odo = np.c_[np.arange(20) * 1.0, np.zeros(20), np.zeros(20)]
    hue = np.zeros((20, 4))
    hue[12:, 0] = 1.0                                      # the view changes at image 12
    feats = np.full(20, 100)
    nodes = partition(odo, hue, feats, RouteParams(max_length=5.0, max_features=10_000))
    assert list(np.flatnonzero(np.diff(nodes)) + 1) == [5, 10, 12, 17]
    nodes = partition(odo, np.zeros((20, 4)), feats, RouteParams(max_length=100.0, max_features=350))
    assert list(np.flatnonzero(np.diff(nodes)) + 1) == [3, 6, 9, 12, 15, 18]


def test_loop_closure_and_relaxation_bring_the_nodes_back():
    rng = np.random.default_rng(0)
    truth, odo = _taught_loop(rng)
    hue = _appearance(truth)
    route = build_route(odo, hue, np.full(len(odo), 300), verify=_verify(truth),
                        params=RouteParams(appearance_threshold=10.0, loop_candidates=8))
    assert route.loop_arcs >= 1
    starts = route.node_images
    before = np.hypot(*(route.node_odometry[:, :2] - truth[starts, :2]).T)
    after = np.hypot(*(route.node_poses[:, :2] - truth[starts, :2]).T)
    assert before.max() > 3.0
    assert after.max() < 0.5 * before.max()
    assert after.mean() < 0.4 * before.mean()
    # every image sits relative to its node, so the taught path follows the nodes
    assert np.allclose(route.path[starts], route.node_poses)
    assert len(route.image_nodes) == len(odo)


def test_without_a_verifier_there_is_no_loop_and_odometry_stands():
    rng = np.random.default_rng(1)
    truth, odo = _taught_loop(rng)
    route = build_route(odo, _appearance(truth), np.full(len(odo), 300),
                        params=RouteParams(appearance_threshold=10.0))
    assert route.loop_arcs == 0
    assert np.allclose(route.node_poses[:, :2], route.node_odometry[:, :2], atol=1e-6)


def test_absolute_positions_move_the_route_onto_them():
    rng = np.random.default_rng(2)
    truth, odo = _taught_loop(rng, drift_deg_per_m=0.0)
    gps = truth[:, :2] * 1.0
    theta = 0.7
    rot = np.array([[math.cos(theta), -math.sin(theta)], [math.sin(theta), math.cos(theta)]])
    gps = gps @ rot.T + [100.0, -50.0]
    gps[::3] = np.nan                                     # GPS is optional per image
    route = build_route(odo, _appearance(truth), np.full(len(odo), 300), positions=gps,
                        params=RouteParams(appearance_threshold=10.0))
    ok = np.isfinite(gps).all(axis=1)
    err = np.hypot(*(route.path[ok, :2] - gps[ok]).T)
    assert err.mean() < 0.3


def test_bad_odometry_is_refused():
    with pytest.raises(ValueError, match="NaN"):
        build_route(np.array([[0, 0, 0], [1, np.nan, 0]], float), np.zeros((2, 3)), np.ones(2))
    with pytest.raises(ValueError, match="positive"):
        RouteParams(max_length=0)
