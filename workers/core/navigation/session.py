"""A localiser that also follows a route: each estimate carries the path following.

The service opens a session that follows a route with
:func:`make_navigating_localiser` instead of :func:`~workers.core.localisers.make_localiser`;
the localiser's estimate is the fix the :class:`~.follower.PathFollower` fuses, and the
estimate carries the path following as its ``navigation`` (:meth:`.NavigationStep.to_dict`).
"""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np

from ..estimate import Estimate, Status
from ..image import WORK_SIZE
from ..localisers import make_localiser, pack_state, unpack_state
from ..localisers.base import as_query
from ..mapdata import MapData
from .follower import FollowerConfig, PathFollower
from .path import Path
from .visual import (
    MAX_REACH,
    Triangulation,
    camera_matrix,
    metric_view,
    relative_view,
    triangulate_views,
)

WINDOW_BEHIND_M, WINDOW_AHEAD_M = 3.0, 6.0
"""Once the robot's place on the route is known, the frame is matched against the taught
images from this far behind it to this far ahead (Li et al.: the coarse stage finds the
node, then SIFT against that part of the map localises accurately)."""

FACTORY = "vloc.workers.core.navigation.session:make_navigating_localiser"
MIN_POSITION_SIGMA = 0.2
"""Metres: a localiser's stated spread is floored here before the EKF trusts it (a single
best map image says "here" with no spread at all)."""
ALONG_SIGMA = 1.0
LATERAL_SIGMA = 2.0
"""Metres: a taught image that looks like the frame places the robot about where it was
taken along the path, and hardly at all beside it (a forward view changes little with a
sidestep of a metre); the bearings from the taught images behind it do that."""
BEARING_SIGMA = math.radians(20.0)
"""The bearing at which a taught image sees the robot (the essential matrix's direction of
translation over a baseline of a metre or two) was 15-25 degrees off on rendered street
frames 1 m beside the path: a weak hint, weighed as one."""
METRIC_FLOOR_M, METRIC_FLOOR_RAD = 0.05, math.radians(0.5)
"""Floors of a triangulated-point pose's standard deviations (:func:`.visual.metric_view`):
the taught path's own positions are not exact."""
AGREEMENT_CHI2 = 11.3
"""99 % quantile of chi-square with 3 degrees of freedom: two triangulated-point poses
further apart than this disagree."""
TRIANGULATION_BASELINES_M = (1.0, 2.0, 3.0)
"""A taught image's points, which a frame's pose is solved against, are triangulated with the
nearest taught images at least these distances behind it and ahead of it along the path, and
fused (:func:`.visual.fuse`). On 240 rendered frames 1-1.5 m beside the path and up to 25
degrees turned, against the one taught image 1 m behind: a pose from 15 points or more on
121 frames instead of 45, placed at 0.95 of the offset instead of 0.82 (median, at 1.5 m),
0.10 m off beside the path instead of 0.27 (median)."""
HEADING_SIGMA = math.radians(5.0)
"""The heading from the relative rotations to the taught images behind the best one: they
were 2-6 degrees off on rendered street frames 20 degrees off the path."""
METRIC_MIN_INLIERS = 15
"""A triangulated-point pose on fewer agreeing points is not used: on rendered street frames
those on 10-12 points were more than 1 m off beside the path one time in five, with a
stated uncertainty of a tenth of that; from 15 points on, the errors are half as large."""
YAW_AGREEMENT = math.radians(10.0)
START_CANDIDATES = 3
"""Best-scoring places checked for a triangulated-point pose until one confirms the robot's
place on the route."""
RESEARCH_VERIFIED = 12
"""Taught images, those with the most ratio-test matches, verified by a fundamental matrix
on each frame while the filter runs with its place unconfirmed."""
VISUAL_DEFAULTS = {"visual": True, "hfov_deg": 60.0, "views": 4}
"""``visual``: measure the robot's pose against the taught images near the best one;
``hfov_deg``: the robot camera's horizontal field of view; ``views``: how many taught
images either side of the best one are looked at for a triangulated-point pose (behind it
only, for bearings)."""


def make_navigating_localiser(mode: str, map_data: MapData, params: dict | None = None, *,
                              seed: int = 0) -> NavigatingLocaliser:
    """Like :func:`~workers.core.localisers.make_localiser`, with ``params["navigation"]``:
    ``points`` ((N, 2) taught path, map frame), ``nodes`` (the route node of each point)
    and ``params`` (:class:`~.follower.FollowerConfig` fields)."""
    params = dict(params or {})
    nav = params.pop("navigation")
    return NavigatingLocaliser(make_localiser(mode, map_data, params, seed=seed), nav)


def navigation_params(given: dict) -> dict:
    """Complete navigation parameters: :data:`VISUAL_DEFAULTS` and the follower's.

    Raises
    ------
    ValueError
        An unknown parameter or a value out of range.
    """
    params = {**VISUAL_DEFAULTS, **given}
    visual = {k: params.pop(k) for k in VISUAL_DEFAULTS}
    if not isinstance(visual["visual"], bool):
        raise ValueError("visual must be true or false")
    if not isinstance(visual["hfov_deg"], int | float) or not 1 <= visual["hfov_deg"] <= 179:
        raise ValueError("hfov_deg must be between 1 and 179 degrees")
    if not isinstance(visual["views"], int) or isinstance(visual["views"], bool) \
            or not 0 <= visual["views"] <= 20:
        raise ValueError("views must be an integer from 0 to 20")
    return {**visual, **FollowerConfig.from_params(params).to_params()}


def node_starts(path: Path, points: np.ndarray, nodes: list[int]) -> tuple[np.ndarray, list[int]]:
    """Arc length along ``path`` at which each route node begins, and the node numbers."""
    s, hint = [], None
    for p in points:
        hint = path.project(p, s_hint=hint).s
        s.append(hint)
    starts, ids = [], []
    for k, node in enumerate(nodes):
        if not ids or node != ids[-1]:
            ids.append(int(node))
            starts.append(0.0 if not starts else s[k])
    return np.array(starts), ids


class NavigatingLocaliser:
    """A localiser and a path follower driven by its estimates.

    When the localiser's best map image is one of the route's taught images, the fix is
    that image's pose on the taught path (so that fixes and path share the route's frame),
    uncertain along the path by :data:`ALONG_SIGMA` and beside it by
    :data:`LATERAL_SIGMA`; with ``visual``, the relative pose of the frame to the taught
    images just behind adds the robot's heading and the bearings at which those images see
    it (:mod:`.visual`), which place it beside the path.
    """

    def __init__(self, inner, navigation: dict) -> None:
        params = {**VISUAL_DEFAULTS, **navigation.get("params", {})}
        self.visual = bool(params.pop("visual"))
        hfov, self.views = float(params.pop("hfov_deg")), int(params.pop("views"))
        points = np.asarray(navigation["points"], np.float64)
        self.inner = inner
        self.config = FollowerConfig.from_params(params)
        self.points = points
        self.thetas = np.asarray(navigation.get("thetas") or _headings(points), np.float64)
        self.path = Path(points)
        self.node_s, self.node_ids = node_starts(self.path, points, list(navigation["nodes"]))
        self.follower = PathFollower(self.path, self.node_s, self.config)
        names = navigation.get("names") or []
        index = {n: i for i, n in enumerate(getattr(inner.map, "names", ()))}
        self.map_index = [index.get(n, -1) for n in names]
        self.route_index = {m: k for k, m in enumerate(self.map_index) if m >= 0}
        self.K = camera_matrix(WORK_SIZE[0], WORK_SIZE[1], hfov)
        self.point_s = np.array(_arc_lengths(self.path, points))
        self._triangulations: dict[int, Triangulation | None] = {}
        self.placed = False
        """Whether a triangulated-point pose has confirmed the robot's place on the route."""
        # this frame's triangulated-point poses by best image (one frame may ask twice)
        self._memo_feats, self._memo = None, {}

    @property
    def mode(self) -> str:
        return self.inner.mode

    @property
    def stats(self) -> dict:
        return self.inner.stats

    def step(self, frame, *, captured_at: float | None = None, metadata=None) -> Estimate:
        query = as_query(frame, captured_at, metadata)
        est = self.inner.step(query)
        fix: dict = {}
        if est.status == Status.TRACKING:
            k = self._nearby_best(query)
            if k is None:
                k = self.route_index.get(est.best_image)
            fix = self._route_fix(k, query) if k is not None else self._estimate_fix(est)
        nav = self.follower.step(fix.get("xy"), fix.get("cov"), heading=fix.get("heading"),
                                 heading_sigma=fix.get("heading_sigma"),
                                 bearings=fix.get("bearings", ()), captured_at=captured_at)
        if nav is None:
            return est
        out = nav.to_dict()
        out["node"] = self.node_ids[nav.node]
        out["views"] = len(fix.get("bearings", ()))
        return replace(est, navigation=out)

    def _nearby_best(self, query) -> int | None:
        """The taught image the frame matches best near the robot's place on the route;
        None when nothing matches.

        Until a triangulated-point pose (:meth:`_metric_fix`) has confirmed the place, every
        taught image is scored (matches verified by a fundamental matrix): a facade repeated
        elsewhere on the route, seen 20 degrees askew, can outscore the right place, and a
        filter started there would look for the robot only near there. Of the best-scoring
        places, the first where the taught points agree on a pose confirms the place; a
        confirmed place outside the filter's window starts the filter again there. Before
        any is confirmed, the filter starts at the best score.
        """
        if not self.route_index:
            return None
        feats, _ = query.sift()
        raw = None        # ratio-test scores of every taught image, where this frame has them
        if not self.placed:
            near = np.arange(len(self.point_s))
            if self.follower.ekf is not None:
                # while the filter runs unconfirmed, a fundamental matrix for every taught
                # image on every frame tripled a frame's CPU: only the images with the most
                # ratio-test matches are verified (verifying can only lower a score)
                near, counts = self._scores(feats, near, "none")
                raw = np.zeros(len(self.point_s))
                raw[near] = counts
                near = near[np.argsort(-counts, kind="stable")[:RESEARCH_VERIFIED]]
            near, score = self._scores(feats, near, "fundamental")
            if self.visual:
                for i in np.argsort(-score, kind="stable")[:START_CANDIDATES]:
                    k = int(near[i])
                    if score[i] > 0 and self._metric_fix(k, feats) is not None:
                        if self.follower.ekf is not None and k not in self._window():
                            self.follower = PathFollower(self.path, self.node_s, self.config)
                        self.placed = True
                        return k
            if self.follower.ekf is None:
                return int(near[int(np.argmax(score))]) if len(near) and score.max() > 0 \
                    else None
            # without triangulated points the place is never confirmed by them
            self.placed = not self.visual
        if raw is None:
            near, score = self._scores(feats, self._window(), "none")
        else:             # the window's scores were among those just computed
            near = self._window()
            near = near[np.asarray(self.map_index)[near] >= 0]
            score = raw[near]
        if not len(near) or score.max() <= 0:
            return None
        return int(near[int(np.argmax(score))])

    def _window(self) -> np.ndarray:
        """Taught images from :data:`WINDOW_BEHIND_M` behind the filter's place on the route
        to :data:`WINDOW_AHEAD_M` ahead (and as far again as the robot can go in two
        frames)."""
        s = self.follower.s
        ahead = WINDOW_AHEAD_M + 2.0 * self.config.control.v_max * self.config.dt
        return np.flatnonzero((self.point_s >= s - WINDOW_BEHIND_M) & (self.point_s <= s + ahead))

    def _scores(self, feats, near: np.ndarray, verify: str) -> tuple[np.ndarray, np.ndarray]:
        """The taught images among ``near`` that are in the map, and the frame's SIFT
        similarity to each."""
        from ..localisers.scoring import sift_similarity

        near = near[np.asarray(self.map_index)[near] >= 0]
        if not len(near):
            return near, np.zeros(0)
        return near, sift_similarity(feats, self.inner.map, np.asarray(self.map_index)[near],
                                     ratio=0.8, verify=verify)

    def _estimate_fix(self, est: Estimate) -> dict:
        cov = np.array(est.cov, np.float64).reshape(2, 2) + np.eye(2) * MIN_POSITION_SIGMA ** 2
        heading = None
        if est.heading_deg is not None:
            # a compass bearing (clockwise from north) to an angle from east
            heading = math.radians(90.0 - est.heading_deg)
        return {"xy": (est.x, est.y), "cov": cov, "heading": heading}

    def _route_fix(self, k: int, query) -> dict:
        th = self.thetas[k]
        c, s = math.cos(th), math.sin(th)
        rot = np.array([[c, -s], [s, c]])
        cov = rot @ np.diag([ALONG_SIGMA ** 2, LATERAL_SIGMA ** 2]) @ rot.T
        fix = {"xy": self.points[k], "cov": cov}
        if not self.visual:
            return fix
        feats, _ = query.sift()
        metric = self._metric_fix(k, feats)
        if metric is not None:
            return metric
        bearings, yaws = [], []
        for j in range(k, max(k - self.views, 0) - 1, -1):
            if self.map_index[j] < 0:
                continue
            view = relative_view(feats, self.inner.map.sift(self.map_index[j]), self.K)
            if view is None:
                continue
            yaws.append(self.thetas[j] + view.yaw)
            if j < k:          # the best image itself is too close for a bearing
                x, y = self.points[j]
                bearings.append((x, y, self.thetas[j] + view.bearing, BEARING_SIGMA))
        if len(yaws) >= 2:
            heading = math.atan2(sum(math.sin(a) for a in yaws), sum(math.cos(a) for a in yaws))
            # two views that disagree on the heading mean one of them is a false match
            if max(abs(math.remainder(a - heading, 2 * math.pi)) for a in yaws) < YAW_AGREEMENT:
                fix["heading"], fix["heading_sigma"] = heading, HEADING_SIGMA
        fix["bearings"] = bearings
        return fix

    def _metric_fix(self, k: int, feats) -> dict | None:
        """The robot's pose from the points taught images near ``k`` triangulate
        (:func:`.visual.metric_view`): the ``views`` taught images on either side of ``k``,
        each with its points triangulated against the taught images around it
        (:meth:`_triangulation`).

        A pose is fused only where at least one other agrees with it (within
        :data:`AGREEMENT_CHI2`): a facade's repeated windows can match along the epipolar
        lines at the wrong depth and give one confident pose on the path when the robot is
        beside it. Of the sets of poses that agree with one of them, the largest is fused;
        its members see the frame through the same features, so their errors are not
        independent, and the fused covariance is one pose's (the mean of their information),
        not the sum of their information.
        """
        if feats is None:
            return self._agreeing_pose(k, feats)
        if feats is not self._memo_feats:
            self._memo_feats, self._memo = feats, {}
        if k not in self._memo:
            self._memo[k] = self._agreeing_pose(k, feats)
        return self._memo[k]

    def _agreeing_pose(self, k: int, feats) -> dict | None:
        poses = []
        for j in range(max(k - self.views, 0), min(k + self.views, len(self.points) - 1) + 1):
            if self.map_index[j] < 0:
                continue
            view = metric_view(feats, self.inner.map.sift(self.map_index[j]),
                               self._triangulation(j), self.K)
            if view is None or math.hypot(view.forward, view.left) > MAX_REACH \
                    or view.inliers < METRIC_MIN_INLIERS:
                continue
            th = self.thetas[j]
            c, s = math.cos(th), math.sin(th)
            rot = np.eye(3)
            rot[:2, :2] = [[c, -s], [s, c]]
            pose = np.r_[self.points[j] + rot[:2, :2] @ np.array([view.forward, view.left]),
                         th + view.yaw]
            cov = rot @ view.cov @ rot.T + np.diag([METRIC_FLOOR_M ** 2, METRIC_FLOOR_M ** 2,
                                                    METRIC_FLOOR_RAD ** 2])
            poses.append((pose, cov))
        best: list[tuple[np.ndarray, np.ndarray]] = []
        for pose, cov in poses:
            agree = []
            for other, other_cov in poses:
                d = other - pose
                d[2] = math.remainder(d[2], 2 * math.pi)
                if float(d @ np.linalg.solve(cov + other_cov, d)) <= AGREEMENT_CHI2:
                    # the other's heading taken on the same turn as this one's
                    agree.append((pose + d, other_cov))
            if len(agree) > len(best):
                best = agree
        if len(best) < 2:
            return None
        info = [np.linalg.inv(cov) for _, cov in best]
        mean = np.linalg.solve(sum(info), sum(i @ p for i, (p, _) in zip(info, best,
                                                                         strict=True)))
        cov = np.linalg.inv(sum(info) / len(best))
        return {"xy": mean[:2], "cov": cov[:2, :2],
                "heading": float(math.remainder(mean[2], 2 * math.pi)),
                "heading_sigma": math.sqrt(cov[2, 2])}

    def _triangulation(self, j: int) -> Triangulation | None:
        """The points taught image ``j`` shares with the taught images around it
        (:meth:`_partners`), triangulated once per localiser: they depend on the taught
        images only, not on the frame."""
        if j not in self._triangulations:
            others = [(self.inner.map.sift(self.map_index[i]),
                       float(np.hypot(*(self.points[j] - self.points[i]))))
                      for i in self._partners(j)]
            self._triangulations[j] = triangulate_views(
                self.inner.map.sift(self.map_index[j]), others, self.K) if others else None
        return self._triangulations[j]

    def _partners(self, j: int) -> list[int]:
        """The nearest taught images at least each of :data:`TRIANGULATION_BASELINES_M`
        behind taught image ``j`` along the path, then ahead of it, that have a map image."""
        out: list[int] = []
        for step in (-1, 1):
            i = j
            for reach in TRIANGULATION_BASELINES_M:
                while 0 <= i < len(self.points) and abs(self.point_s[i] - self.point_s[j]) < reach:
                    i += step
                if not 0 <= i < len(self.points):
                    break
                if self.map_index[i] >= 0 and i not in out:
                    out.append(i)
        return out

    def get_state(self) -> bytes:
        inner = np.frombuffer(self.inner.get_state(), np.uint8)
        return pack_state({"inner": inner},
                          {"follower": json.loads(json.dumps(self.follower.get_state())),
                           "placed": self.placed})

    def set_state(self, data: bytes) -> None:
        arrays, meta = unpack_state(data)
        self.inner.set_state(arrays["inner"].tobytes())
        self.follower.set_state(meta["follower"])
        self.placed = bool(meta.get("placed", True))

    def reset(self) -> None:
        """Global re-initialisation: the localiser forgets, and the follower starts again
        from the next fix."""
        self.inner.reset()
        self.follower = PathFollower(self.path, self.node_s, self.config)
        self.placed = False

    def set_initial_pose(self, x: float, y: float, sigma: float = 5.0) -> None:
        self.inner.set_initial_pose(x, y, sigma)


def _arc_lengths(path: Path, points: np.ndarray) -> list[float]:
    s, hint = [], None
    for p in points:
        hint = path.project(p, s_hint=hint).s
        s.append(hint)
    return s


def _headings(points: np.ndarray) -> np.ndarray:
    d = np.gradient(points, axis=0)
    return np.arctan2(d[:, 1], d[:, 0])
