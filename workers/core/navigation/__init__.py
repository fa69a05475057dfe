"""Teach and repeat after Li et al.: route maps, relaxation, and path following.

A route is taught by driving it once: the ordered images with odometry are partitioned
into topological nodes (:mod:`.routemap`), arcs carry the relative odometric transforms,
loop closures add arcs between places seen twice, and Duckett et al.'s relaxation makes the
node poses consistent (:mod:`.relaxation`). Repeating the route, an extended Kalman filter
smooths the visual pose fixes (:mod:`.ekf`) and Li et al.'s path-following law (eq. 8)
turns the distance and heading errors into velocity commands (:mod:`.control`);
:mod:`.follower` ties both to a :class:`~.path.Path` and reports progress and arrival.
:mod:`.unicycle` simulates the robot those commands drive.
"""

from .control import ControlConfig, path_following_command
from .ekf import UnicycleEKF
from .follower import FollowerConfig, NavigationStep, PathFollower
from .path import Path, Projection
from .relaxation import Arc, relax
from .routemap import RouteMap, RouteParams, build_route
from .unicycle import ActuationNoise, unicycle_step

__all__ = ["ActuationNoise", "Arc", "ControlConfig", "FollowerConfig", "NavigationStep", "Path",
           "PathFollower", "Projection", "RouteMap", "RouteParams", "UnicycleEKF", "build_route",
           "path_following_command", "relax", "unicycle_step"]
