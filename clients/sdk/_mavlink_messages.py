"""What a pose says to an autopilot: the fields of MAVLink's ``GPS_INPUT``,
``VISION_POSITION_ESTIMATE`` and ``ODOMETRY``, and how often to say it.

Nothing here imports pymavlink: the fields are plain dictionaries, keyword arguments of the
``*_send`` methods pymavlink generates, so the translation is testable without a link.
A pose that is not ``tracking`` gives no message: while initialising or lost its position is
the particles' mean over the whole map, not a fix, and saying nothing lets the autopilot's
GPS timeout declare the loss as it does for a receiver that stops.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from datetime import UTC, datetime, timedelta
from typing import Any

from ._models import Pose

# MAVLink common.xml: GPS_FIX_TYPE and GPS_INPUT_IGNORE_FLAGS
FIX_NONE, FIX_2D, FIX_3D = 1, 2, 3
IGNORE_ALT, IGNORE_HDOP, IGNORE_VDOP = 1, 2, 4
IGNORE_VEL_HORIZ, IGNORE_VEL_VERT, IGNORE_SPEED_ACCURACY = 8, 16, 32
IGNORE_HORIZONTAL_ACCURACY, IGNORE_VERTICAL_ACCURACY = 64, 128
MAV_FRAME_LOCAL_NED, MAV_FRAME_BODY_FRD = 1, 12
MAV_ESTIMATOR_TYPE_VISION = 2

UERE_M = 3.0
"""A GNSS receiver's range error: ``hdop = horizontal_accuracy_m / UERE_M`` makes the
autopilot's HDOP checks (ArduPilot's GPS_HDOP_GOOD, PX4's EKF2_REQ_EPH) read the pose as
they read a receiver of the same accuracy."""

GPS_EPOCH = datetime(1980, 1, 6, tzinfo=UTC)
GPS_LEAP_SECONDS = 18
"""GPS time runs ahead of UTC by the leap seconds since 1980 (18 since 2017)."""

WEEK_S = 7 * 86400


def gps_time(at: datetime) -> tuple[int, int]:
    """``(week, milliseconds into the week)`` of GPS time at ``at`` (timezone-aware)."""
    elapsed = at - GPS_EPOCH + timedelta(seconds=GPS_LEAP_SECONDS)
    ms = int(elapsed.total_seconds() * 1000)
    return ms // (WEEK_S * 1000), ms % (WEEK_S * 1000)


def fix_type(pose: Pose) -> int:
    """No fix unless the pose tracks; a 3-D fix when it carries an altitude, else 2-D."""
    if pose.status != "tracking":
        return FIX_NONE
    return FIX_3D if pose.altitude_m is not None else FIX_2D


def geometry_heading(pose: Pose) -> float | None:
    """The heading the images gave, degrees; None when there was none. A heading with
    ``heading_source == "device"`` is the autopilot's own, sent with the frame: giving it
    back as a measurement would close a loop on the autopilot's yaw."""
    return pose.heading_deg if pose.heading_source == "geometry" else None


def gps_input(pose: Pose, *, at: datetime, gps_id: int = 0) -> dict[str, Any] | None:
    """``GPS_INPUT`` for a tracking pose of a frame captured ``at``; None otherwise.

    The position is the pose's to 1e-7 degrees; ``horiz_accuracy`` is its
    ``horizontal_accuracy_m`` and ``hdop`` the same over :data:`UERE_M`. The altitude is the
    one sent with the frame: the pose has no vertical accuracy of its own, so that and the
    velocities, which it does not estimate, are flagged as ignored. ``yaw`` is the images'
    heading in centidegrees (36000 for north, 0 for unknown).
    """
    if fix_type(pose) == FIX_NONE or pose.horizontal_accuracy_m is None:
        return None
    ignore = IGNORE_VDOP | IGNORE_VEL_HORIZ | IGNORE_VEL_VERT | IGNORE_SPEED_ACCURACY \
        | IGNORE_VERTICAL_ACCURACY
    if pose.altitude_m is None:
        ignore |= IGNORE_ALT
    week, week_ms = gps_time(at)
    heading = geometry_heading(pose)
    yaw = 0 if heading is None else (round(heading * 100) % 36000 or 36000)
    return {
        "time_usec": int(at.timestamp() * 1e6), "gps_id": gps_id, "ignore_flags": ignore,
        "time_week_ms": week_ms, "time_week": week, "fix_type": fix_type(pose),
        "lat": round(pose.lat * 1e7), "lon": round(pose.lon * 1e7),
        "alt": 0.0 if pose.altitude_m is None else float(pose.altitude_m),
        "hdop": pose.horizontal_accuracy_m / UERE_M, "vdop": 0.0,
        "vn": 0.0, "ve": 0.0, "vd": 0.0, "speed_accuracy": 0.0,
        "horiz_accuracy": float(pose.horizontal_accuracy_m), "vert_accuracy": 0.0,
        "satellites_visible": 0, "yaw": yaw,
    }


def _ned(pose: Pose) -> tuple[float, float, float, float, float]:
    """North, east, and the north/east covariance (nn, ne, ee) of a pose."""
    ee, en, _, nn = pose.cov
    return pose.y, pose.x, nn, en, ee


def _yaw_rad(pose: Pose) -> float:
    heading = geometry_heading(pose)
    return math.nan if heading is None else math.radians((heading + 180.0) % 360.0 - 180.0)


UNKNOWN_YAW_VARIANCE = math.pi ** 2 / 3
"""The variance of a heading that may be anything (uniform over the circle), rad^2."""


def vision_position_estimate(pose: Pose, *, usec: int, reset_counter: int = 0
                             ) -> dict[str, Any] | None:
    """``VISION_POSITION_ESTIMATE`` in the map's local frame as NED (x north, y east, metres
    from the map's origin); None unless the pose tracks.

    The covariance is the upper triangle of (x, y, z, roll, pitch, yaw), row-major: the
    pose's horizontal covariance; z, roll and pitch, which the images do not measure, get
    0, and yaw the variance of the images' heading (:data:`UNKNOWN_YAW_VARIANCE` where they
    gave none, with ``yaw`` NaN). Every diagonal element is a number because ArduPilot
    reads the matrix as two sums, ``sqrt(var x + var y + var z)`` as the position's noise
    and ``sqrt(var roll + var pitch + var yaw)`` as the attitude's: one NaN would make the
    estimate's noise NaN, and a large z variance would drown the horizontal one (the
    altitude comes from the barometer, docs/devices/mavlink.md).
    """
    if pose.status != "tracking":
        return None
    north, east, nn, ne, ee = _ned(pose)
    cov = [0.0] * 21
    cov[0], cov[1], cov[6] = nn, ne, ee
    yaw = _yaw_rad(pose)
    cov[20] = UNKNOWN_YAW_VARIANCE if math.isnan(yaw) else \
        math.radians(pose.heading_sigma_deg or 15.0) ** 2
    return {"usec": usec, "x": north, "y": east, "z": 0.0, "roll": 0.0, "pitch": 0.0,
            "yaw": yaw, "covariance": cov, "reset_counter": reset_counter}


def odometry(pose: Pose, *, usec: int, reset_counter: int = 0) -> dict[str, Any] | None:
    """``ODOMETRY`` (MAVLink 2) with the position in the local NED frame and no velocity
    (NaN, as the message allows for unknown values); None unless the pose tracks.

    ``z`` and what the images do not measure are NaN, variances included: PX4's EKF2,
    which this message is for, takes the horizontal position and its x and y variances
    alone when told to (``EKF2_EV_CTRL`` 1) and nothing NaN reaches it. ArduPilot reduces
    this covariance as :func:`vision_position_estimate` says, z's NaN included: for it,
    ``VISION_POSITION_ESTIMATE``.
    """
    if pose.status != "tracking":
        return None
    north, east, nn, ne, ee = _ned(pose)
    yaw = _yaw_rad(pose)
    q = [math.nan, 0.0, 0.0, 0.0] if math.isnan(yaw) else \
        [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]
    pose_cov = [math.nan] * 21
    pose_cov[0], pose_cov[1], pose_cov[6] = nn, ne, ee
    if not math.isnan(yaw):
        pose_cov[20] = math.radians(pose.heading_sigma_deg or 15.0) ** 2
    return {"time_usec": usec, "frame_id": MAV_FRAME_LOCAL_NED,
            "child_frame_id": MAV_FRAME_BODY_FRD, "x": north, "y": east, "z": math.nan,
            "q": q, "vx": math.nan, "vy": math.nan, "vz": math.nan, "rollspeed": math.nan,
            "pitchspeed": math.nan, "yawspeed": math.nan, "pose_covariance": pose_cov,
            "velocity_covariance": [math.nan] * 21, "reset_counter": reset_counter,
            "estimator_type": MAV_ESTIMATOR_TYPE_VISION, "quality": -1}


def map_origin(pose: Pose) -> tuple[float, float]:
    """The (lat, lon) of the map's origin, from one pose's position in both frames: the local
    frame is a tangent plane, so over a map's few kilometres a step back by (x, y) metres on
    the WGS84 ellipsoid's radii of curvature there is within centimetres of the geodesy the
    service does."""
    a, e2 = 6378137.0, 6.69437999014e-3
    s2 = math.sin(math.radians(pose.lat)) ** 2
    meridian = a * (1 - e2) / (1 - e2 * s2) ** 1.5
    normal = a / math.sqrt(1 - e2 * s2)
    lat = pose.lat - math.degrees(pose.y / meridian)
    lon = pose.lon - math.degrees(pose.x / (normal * math.cos(math.radians(lat))))
    return lat, lon


class RateLimiter:
    """At most ``max_hz`` messages a second: :meth:`allow` says whether one may go now.

    A message that may not go is dropped, never delayed: by the time it could, a newer pose
    is due (what the autopilot wants is the latest position, not a backlog).
    """

    def __init__(self, max_hz: float, clock: Callable[[], float] = time.monotonic) -> None:
        if max_hz <= 0:
            raise ValueError("max_hz must be positive")
        self.interval = 1.0 / max_hz
        self._clock = clock
        self._last: float | None = None

    def allow(self) -> bool:
        now = self._clock()
        if self._last is not None and now - self._last < self.interval:
            return False
        self._last = now
        return True
