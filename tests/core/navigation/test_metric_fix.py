"""The navigating localiser's fix from triangulated taught views: agreement, then fusion."""

import math
from types import SimpleNamespace

import numpy as np
import pytest

from vloc.workers.core.navigation import session
from vloc.workers.core.navigation.session import NavigatingLocaliser
from vloc.workers.core.navigation.visual import MetricView


def _localiser(n: int = 12, spacing: float = 0.6) -> NavigatingLocaliser:
    """A straight taught path east along y = 0, one map image per taught point."""
    names = [f"f{i:03d}.jpg" for i in range(n)]
    inner = SimpleNamespace(map=SimpleNamespace(names=tuple(names), sift=lambda i: i))
    points = [[spacing * i, 0.0] for i in range(n)]
    return NavigatingLocaliser(inner, {"points": points, "nodes": [0] * n, "names": names})


def _view(forward, left, yaw, sigma=0.1, yaw_sigma=math.radians(1.0), inliers=30):
    return MetricView(forward, left, yaw, np.diag([sigma ** 2, sigma ** 2, yaw_sigma ** 2]),
                      inliers)


def test_two_agreeing_views_are_fused_by_their_information(monkeypatch):
    loc = _localiser()
    # the robot at (5.0, 0.8) heading 10 degrees left of east, seen from taught images 8
    # and 7 (at 4.8 and 4.2 m); image 7's view is twice as sure
    views = {8: _view(0.2, 0.8, math.radians(10.0), sigma=0.2),
             7: _view(0.8 + 0.02, 0.8, math.radians(10.5), sigma=0.1)}
    calls = []

    def fake(feats, ref, tri, K):
        calls.append(tri)
        return views.get(ref)

    monkeypatch.setattr(session, "triangulate_views", lambda ref, others, K:
                        (ref, [(o, pytest.approx(b)) for o, b in others]))
    monkeypatch.setattr(session, "metric_view", fake)
    fix = loc._metric_fix(8, feats=None)
    # each view is triangulated against the nearest taught images at least 1, 2 and 3 m
    # behind it and ahead of it (the path ends at 6.6 m), with their distances
    assert (8, [(6, 1.2), (4, 2.4), (3, 3.0), (10, 1.2)]) in calls
    assert (7, [(5, 1.2), (3, 2.4), (2, 3.0), (9, 1.2), (11, 2.4)]) in calls
    # information-weighted mean: weights 1 / (s^2 + floor^2) per axis
    w8, w7 = 1 / (0.2 ** 2 + 0.05 ** 2), 1 / (0.1 ** 2 + 0.05 ** 2)
    assert fix["xy"][0] == pytest.approx((w8 * 5.0 + w7 * 5.02) / (w8 + w7), abs=1e-9)
    assert fix["xy"][1] == pytest.approx(0.8, abs=1e-9)
    # the two views share the frame's features: the fused pose is as sure as one view of
    # their mean information, not as both together
    assert fix["cov"][0, 0] == pytest.approx(2 / (w8 + w7))
    assert math.degrees(fix["heading"]) == pytest.approx(10.25, abs=0.01)


def test_views_ahead_of_the_best_image_count_too(monkeypatch):
    loc = _localiser()
    # the robot at (5.0, 0.8): seen from taught images 9 and 10 (at 5.4 and 6.0 m), ahead
    # of the best image 8, which has no view
    views = {9: _view(-0.4, 0.8, 0.0), 10: _view(-1.0, 0.8, 0.0)}
    monkeypatch.setattr(session, "triangulate_views", lambda *a: "points")
    monkeypatch.setattr(session, "metric_view", lambda f, ref, tri, K: views.get(ref))
    fix = loc._metric_fix(8, feats=None)
    assert fix["xy"] == pytest.approx([5.0, 0.8], abs=1e-9)


def test_the_largest_set_of_agreeing_views_is_fused(monkeypatch):
    loc = _localiser()
    # two views agree on the path (a repeated facade), three agree 0.8 m beside it
    views = {4: _view(0.2, 0.0, 0.0), 5: _view(-0.4, 0.0, 0.0),
             7: _view(0.8, 0.8, 0.0), 8: _view(0.2, 0.8, 0.0), 10: _view(-1.0, 0.8, 0.0)}
    monkeypatch.setattr(session, "triangulate_views", lambda *a: "points")
    monkeypatch.setattr(session, "metric_view", lambda f, ref, tri, K: views.get(ref))
    assert loc._metric_fix(8, feats=None)["xy"] == pytest.approx([5.0, 0.8], abs=1e-9)


def test_views_that_disagree_give_no_fix(monkeypatch):
    loc = _localiser()
    # one view puts the robot on the path, the other a metre beside it: repeated facades
    # matched at the wrong depth look like this
    views = {8: _view(0.2, 0.0, 0.0), 7: _view(0.8, 1.0, math.radians(2.0)),
             6: _view(1.4, -1.0, 0.0)}
    monkeypatch.setattr(session, "triangulate_views", lambda *a: "points")
    monkeypatch.setattr(session, "metric_view", lambda f, ref, tri, K: views.get(ref))
    assert loc._metric_fix(8, feats=None) is None


def test_a_view_on_too_few_points_is_not_used(monkeypatch):
    loc = _localiser()
    few = session.METRIC_MIN_INLIERS - 1
    views = {8: _view(0.2, 0.8, 0.0, inliers=few), 7: _view(0.8, 0.8, 0.0),
             6: _view(1.4, 0.8, 0.0, inliers=few)}
    monkeypatch.setattr(session, "triangulate_views", lambda *a: "points")
    monkeypatch.setattr(session, "metric_view", lambda f, ref, tri, K: views.get(ref))
    assert loc._metric_fix(8, feats=None) is None
    views[6] = _view(1.4, 0.8, 0.0, inliers=few + 1)
    assert loc._metric_fix(8, feats=None)["xy"][1] == pytest.approx(0.8)


def test_a_view_beyond_reach_is_not_used(monkeypatch):
    loc = _localiser()
    views = {8: _view(6.0, 0.0, 0.0), 7: _view(6.6, 0.0, 0.0)}
    monkeypatch.setattr(session, "triangulate_views", lambda *a: "points")
    monkeypatch.setattr(session, "metric_view", lambda f, ref, tri, K: views.get(ref))
    assert loc._metric_fix(8, feats=None) is None


def test_the_taught_points_are_triangulated_once(monkeypatch):
    loc = _localiser()
    pairs = []
    monkeypatch.setattr(session, "triangulate_views",
                        lambda ref, others, K: pairs.append(ref))
    monkeypatch.setattr(session, "metric_view", lambda f, ref, tri, K: None)
    loc._metric_fix(8, feats=None)
    loc._metric_fix(8, feats=None)
    # the taught images four either side of image 8 (the path ends at 11), once each
    assert pairs == [4, 5, 6, 7, 8, 9, 10, 11]


def test_the_partners_are_the_nearest_images_1_2_and_3_m_behind_then_ahead():
    loc = _localiser(spacing=0.5)
    assert loc._partners(8) == [6, 4, 2, 10]  # 2 m ahead is past the path's end
    assert loc._partners(0) == [2, 4, 6]
    # a taught point without a map image is passed over for the next one
    loc.map_index[6] = -1
    assert loc._partners(8) == [4, 2, 10]


def test_a_taught_image_alone_gives_no_view(monkeypatch):
    loc = _localiser(n=2, spacing=0.5)
    monkeypatch.setattr(session, "triangulate_views",
                        lambda *a: pytest.fail("needs two taught images 1 m apart"))
    assert loc._metric_fix(0, feats=None) is None


def _scored(monkeypatch, loc, scores: dict[int, float], views: dict):
    """The frame's SIFT scores against the taught images (by taught index) and the metric
    views of the taught images, patched in."""
    from vloc.workers.core.localisers import scoring

    monkeypatch.setattr(scoring, "sift_similarity", lambda feats, m, idx, ratio, verify:
                        np.array([scores.get(int(i), 0.0) for i in idx]))
    monkeypatch.setattr(session, "triangulate_views", lambda *a: "points")
    monkeypatch.setattr(session, "metric_view", lambda f, ref, tri, K: views.get(ref))
    return SimpleNamespace(sift=lambda: ("feats", None))


def test_the_filter_starts_where_the_taught_points_agree(monkeypatch):
    loc = _localiser(n=30)
    # a repeated facade at image 5 outscores the right place, image 20, where two taught
    # views agree on a pose
    query = _scored(monkeypatch, loc, {5: 40.0, 20: 30.0, 25: 10.0},
                    {19: _view(0.6, 0.8, 0.0), 21: _view(-0.6, 0.8, 0.0)})
    assert loc._nearby_best(query) == 20


def test_without_agreeing_taught_points_the_best_score_starts_the_filter(monkeypatch):
    loc = _localiser(n=30)
    query = _scored(monkeypatch, loc, {5: 40.0, 20: 30.0}, {})
    assert loc._nearby_best(query) == 5


def test_once_placed_the_best_score_near_the_robot_is_taken(monkeypatch):
    loc = _localiser(n=30)
    query = _scored(monkeypatch, loc, {5: 40.0, 6: 35.0, 20: 30.0},
                    {19: _view(0.6, 0.8, 0.0), 21: _view(-0.6, 0.8, 0.0)})
    loc.follower.step((0.6 * 5, 0.0), np.eye(2))         # at image 5, confirmed there
    loc.placed = True
    assert loc._nearby_best(query) == 5


def test_a_confirmed_place_elsewhere_starts_the_filter_again(monkeypatch):
    loc = _localiser(n=30)
    # the first frames placed the robot at image 5 without agreeing taught points...
    query = _scored(monkeypatch, loc, {5: 40.0}, {})
    assert loc._nearby_best(query) == 5
    loc.follower.step((0.6 * 5, 0.0), np.eye(2))
    assert not loc.placed
    # ...then a frame whose taught points agree at image 20, outside the filter's window
    query = _scored(monkeypatch, loc, {5: 40.0, 20: 30.0},
                    {19: _view(0.6, 0.8, 0.0), 21: _view(-0.6, 0.8, 0.0)})
    assert loc._nearby_best(query) == 20
    assert loc.placed and loc.follower.ekf is None        # starts from this frame's fix
    # confirmed inside the window, the filter is kept
    loc = _localiser(n=30)
    query = _scored(monkeypatch, loc, {5: 40.0, 7: 30.0},
                    {6: _view(0.6, 0.8, 0.0), 8: _view(-0.6, 0.8, 0.0)})
    loc.follower.step((0.6 * 5, 0.0), np.eye(2))
    assert loc._nearby_best(query) == 5 and loc.placed and loc.follower.ekf is not None


def test_whether_the_place_is_confirmed_is_checkpointed(monkeypatch):
    loc = _localiser(n=30)
    monkeypatch.setattr(loc.inner, "get_state", lambda: b"inner", raising=False)
    monkeypatch.setattr(loc.inner, "set_state", lambda data: None, raising=False)
    loc.follower.step((0.6 * 5, 0.0), np.eye(2))
    loc.placed = True
    other = _localiser(n=30)
    other.inner.set_state = lambda data: None
    other.set_state(loc.get_state())
    assert other.placed
    assert other.follower.get_state() == loc.follower.get_state()
