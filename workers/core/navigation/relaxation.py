"""Relaxation of a topological map's node poses (Duckett, Marsland and Shapiro 2000, as
given by Li et al., eqs. 1-3).

Every node holds a pose ``(x, z, theta)`` (here ``(x, y, theta)``) and a variance; every arc
the relative pose of its two nodes, measured by odometry or by recognising a place again,
with its own variance. One sweep visits each node in turn and replaces its pose by the
variance-weighted mean of the poses its neighbours predict for it (eq. 1 and 3) and its
variance by the harmonic mean of theirs (eq. 2); sweeps repeat until the total change in
the coordinates falls under a threshold (headings first, then positions; see :func:`relax`). The first node is the reference frame: fixed, with
a small variance. Updating in place (Gauss-Seidel, as Duckett et al. do) passes a loop
closure's correction round the loop faster than updating all nodes from the last sweep.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

REFERENCE_VARIANCE = 1e-6
OVER_RELAXATION = 1.7
"""Each sweep moves a node this many times the way to its neighbours' weighted mean
(successive over-relaxation): the same fixed point, reached in far fewer sweeps along a
long chain."""


@dataclass(frozen=True, slots=True)
class Arc:
    """A relation between nodes ``a`` and ``b``: the pose of ``b`` in ``a``'s frame.

    Attributes
    ----------
    a, b : int
        Node indices.
    dx, dy : float
        Position of ``b`` in ``a``'s frame (x forward, y left), metres.
    dtheta : float
        Heading of ``b`` minus heading of ``a``, radians.
    variance : float
        The arc's variance ``omega_ab`` (m^2), e.g. growing with the distance driven.
    """

    a: int
    b: int
    dx: float
    dy: float
    dtheta: float
    variance: float


@dataclass(frozen=True)
class RelaxResult:
    """Relaxed poses ``(N, 3)``, node variances ``(N,)``, sweeps run, and whether the
    change fell under the threshold."""

    poses: np.ndarray
    variances: np.ndarray
    sweeps: int
    converged: bool


def predict(pose_from: tuple[float, float, float], arc: Arc, forward: bool
            ) -> tuple[float, float, float]:
    """The pose that ``arc`` gives one end from the other end's pose (Li eq. 1).

    ``forward`` predicts ``b`` from ``a``; otherwise ``a`` from ``b``.
    """
    x, y, th = pose_from
    if forward:
        c, s = math.cos(th), math.sin(th)
        return x + c * arc.dx - s * arc.dy, y + s * arc.dx + c * arc.dy, th + arc.dtheta
    th_a = th - arc.dtheta
    c, s = math.cos(th_a), math.sin(th_a)
    return x - (c * arc.dx - s * arc.dy), y - (s * arc.dx + c * arc.dy), th_a


def relax(poses: np.ndarray, arcs: list[Arc], *, variances: np.ndarray | None = None,
          tol: float = 1e-4, max_sweeps: int = 5000, node_variances: bool = True
          ) -> RelaxResult:
    """Duckett et al.'s iterative relaxation (Li et al. eqs. 1-3).

    Parameters
    ----------
    poses : (N, 3) float ndarray
        Initial node poses ``(x, y, theta)``, e.g. from odometry; node 0 is the reference and
        stays where it is.
    arcs : list of Arc
    variances : (N,) float ndarray, optional
        Initial node variances; by default each node starts with the variance accumulated
        along the arcs from node 0 (Li: "initialized with the variance of the previous node").
    tol : float
        Stop when the summed absolute change of the headings (rad), then of x and y (m),
        over one sweep falls under it.
    max_sweeps : int
    node_variances : bool
        Weigh a neighbour's prediction by ``1 / (omega_j + omega_ij)`` as eq. 1-3 do
        (True), or by the arc's own ``1 / omega_ij`` (False). The paper's weights count the
        neighbour's variance twice over a loop, and pull the correction of a loop closure
        towards the nodes furthest from the reference; the arc weights make the fixed point
        the weighted least-squares one and spread it in proportion to the arcs' variances.

    Returns
    -------
    RelaxResult
    """
    pose = [tuple(float(v) for v in p) for p in np.asarray(poses, np.float64)]
    n = len(pose)
    incident: list[list[tuple[Arc, bool]]] = [[] for _ in range(n)]
    for arc in arcs:
        if not (0 <= arc.a < n and 0 <= arc.b < n) or arc.a == arc.b:
            raise ValueError(f"arc {arc.a}->{arc.b} does not join two distinct nodes of {n}")
        if not arc.variance > 0:
            raise ValueError(f"arc {arc.a}->{arc.b} needs a positive variance")
        incident[arc.b].append((arc, True))     # b is predicted forward from a
        incident[arc.a].append((arc, False))
    var = _initial_variances(n, arcs) if variances is None else \
        [float(v) for v in np.asarray(variances, np.float64)]
    var[0] = REFERENCE_VARIANCE
    # The headings and variances of eqs. 1-3 do not depend on the positions, and with the
    # headings known the positions are a linear problem: relaxing the headings first and
    # then the positions reaches the same fixed point as updating all at once, without
    # letting a position pass through a heading that is still far off (a loop closing
    # 30 degrees of drift can otherwise settle twisted).
    heading_sweeps, heading_done = _sweeps(n, incident, pose, var, tol, max_sweeps,
                                           headings=True, node_variances=node_variances)
    sweeps, converged = _sweeps(n, incident, pose, var, tol, max_sweeps, headings=False,
                                node_variances=node_variances)
    out = np.array(pose)
    out[:, 2] = np.remainder(out[:, 2] + math.pi, 2 * math.pi) - math.pi
    return RelaxResult(poses=out, variances=np.array(var),
                       sweeps=heading_sweeps + sweeps, converged=heading_done and converged)


def _sweeps(n, incident, pose, var, tol, max_sweeps, *, headings: bool,
            node_variances: bool) -> tuple[int, bool]:
    """Gauss-Seidel sweeps of eqs. 1-3 over the headings and variances, or over the
    positions with the headings held, until the summed change falls under ``tol``."""
    sweeps, converged = 0, n < 2
    while not converged and sweeps < max_sweeps:
        sweeps += 1
        change = 0.0
        for i in range(1, n):
            if not incident[i]:
                continue
            sw = sx = sy = ss = sc = 0.0
            for arc, forward in incident[i]:
                j = arc.a if forward else arc.b
                # 1 / (omega'_i)_j of eq. 1, or the arc's weight alone
                w = 1.0 / (var[j] + arc.variance if node_variances else arc.variance)
                sw += w
                if headings:
                    th = pose[j][2] + (arc.dtheta if forward else -arc.dtheta)
                    ss += w * math.sin(th)
                    sc += w * math.cos(th)
                elif forward:
                    xj, yj, _ = predict(pose[j], arc, True)
                else:
                    # the arc's translation is in this node's frame: turn it by this node's
                    # relaxed heading, not by the neighbour's heading less the arc's turn,
                    # which still carries the odometry's heading error
                    c, s_ = math.cos(pose[i][2]), math.sin(pose[i][2])
                    xj = pose[j][0] - (c * arc.dx - s_ * arc.dy)
                    yj = pose[j][1] - (s_ * arc.dx + c * arc.dy)
                if not headings:
                    sx += w * xj
                    sy += w * yj
            x, y, th = pose[i]
            if headings:
                # eq. 3, circular mean, over-relaxed
                step = math.remainder(math.atan2(ss, sc) - th, 2 * math.pi)
                th = th + OVER_RELAXATION * step
                change += abs(step)
                var[i] = len(incident[i]) / sw            # eq. 2
            else:
                dx, dy = sx / sw - x, sy / sw - y         # eq. 3, over-relaxed
                x, y = x + OVER_RELAXATION * dx, y + OVER_RELAXATION * dy
                change += abs(dx) + abs(dy)
            pose[i] = (x, y, th)
        converged = change < tol
    return sweeps, converged


def _initial_variances(n: int, arcs: list[Arc]) -> list[float]:
    """Each node's variance as the sum of arc variances along the first path found to it
    from node 0 (breadth first); unreachable nodes get the largest of those."""
    var = [math.inf] * n
    var[0] = REFERENCE_VARIANCE
    frontier = [0]
    adj: list[list[tuple[int, float]]] = [[] for _ in range(n)]
    for arc in arcs:
        adj[arc.a].append((arc.b, arc.variance))
        adj[arc.b].append((arc.a, arc.variance))
    while frontier:
        nxt = []
        for i in frontier:
            for j, v in adj[i]:
                if var[j] == math.inf:
                    var[j] = var[i] + v
                    nxt.append(j)
        frontier = nxt
    finite = [v for v in var if v < math.inf]
    return [v if v < math.inf else max(finite) for v in var]


def relative_pose(pose_a, pose_b) -> tuple[float, float, float]:
    """The pose of ``b`` in ``a``'s frame: ``(dx, dy, dtheta)`` for an :class:`Arc`."""
    xa, ya, tha = (float(v) for v in pose_a)
    xb, yb, thb = (float(v) for v in pose_b)
    c, s = math.cos(tha), math.sin(tha)
    dx, dy = xb - xa, yb - ya
    dth = math.atan2(math.sin(thb - tha), math.cos(thb - tha))
    return c * dx + s * dy, -s * dx + c * dy, dth
