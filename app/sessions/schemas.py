"""Bodies of the session routes and the messages of the pose stream."""

from __future__ import annotations

import math
import uuid
from datetime import datetime
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, computed_field, model_validator

from vloc.workers.core.estimate import Status
from vloc.workers.core.modes import MODES

MAX_SEQ = 2**63 - 1
"""The largest frame sequence number: the database stores it as a signed 64-bit integer."""

Seq = Annotated[int, Field(ge=0, le=MAX_SEQ, strict=True,
                           description=f"Frame sequence number, 0 to {MAX_SEQ}")]

MAX_INITIAL_SIGMA_M = 1000.0
"""A wider prior than this is no prior: use reset (particles over the whole map)."""


class SessionStats(BaseModel):
    sift_share: float | None = Field(description="Share of estimates that used SIFT")
    latency_ms_p50: float | None
    latency_ms_p99: float | None
    processing_ms_mean: float | None


class NavigationState(BaseModel):
    """Path following after one estimate (Li et al.): the EKF state, the command of the
    control law, the reference point on the path, and where along the route."""

    state: dict[str, float] = Field(description="EKF mean: x, y (m), theta (rad from east), "
                                                "v (m/s), omega (rad/s)")
    command: dict[str, float] = Field(description="v (m/s), omega (rad/s) to drive")
    reference: dict[str, float] = Field(description="Closest path point x, y and the path's "
                                                    "heading theta there")
    cross_track: float = Field(description="Signed distance to the path, m, left positive")
    heading_error: float = Field(description="Radians")
    curvature: float = Field(description="Path curvature at the reference point, 1/m")
    node: int = Field(description="Route node of the reference point")
    progress: float = Field(description="Metres of path behind the reference point")
    length: float = Field(description="Metres of path in all")
    arrived: bool
    fused: bool = Field(description="Whether this frame's fix was fused (not gated out)")
    views: int | None = Field(None, description="Taught views that gave a bearing this frame")



class Quaternion(BaseModel):
    """A unit quaternion (``x``, ``y``, ``z`` vector part, ``w`` scalar)."""

    x: float
    y: float
    z: float
    w: float


class GeoPosePosition(BaseModel):
    lat: float
    lon: float
    h: float = Field(description="Height in metres (``altitude_m``)")


class GeoPose(BaseModel):
    """The pose in the form of OGC GeoPose 1.0 Basic-Quaternion.

    The quaternion turns the local East-North-Up tangent frame at ``position`` into the
    camera's frame, the heading as a rotation about Up (yaw = 90 deg - heading); the
    localiser estimates no pitch or roll, so none is applied. It is null when the heading
    is unknown: an orientation is never made up.
    """

    position: GeoPosePosition
    quaternion: Quaternion | None


# The definitions of the fields that say how a pose was found: docs/api.md's table gives
# these same words (tests/app/test_pose_definition.py holds them together).
FEATURE = ("The image feature the step matched: sift when it extracted SIFT (to weigh the "
           "particles, or to register the camera when the global features' registration "
           "failed), global when it used global features only; the feature's name for "
           "retrieval")
NEXT_FEATURE = "What the filter will use for the next frame: sift or global"
MEASUREMENT = ("What weighed the estimate, joined by +: sift or global (the image similarity "
               "that weighed the particles), registered (a camera pose solved against the "
               "map), interpolated (between the best map images); empty when not known. "
               "global+registered with feature sift is a global step whose camera pose was "
               "solved with SIFT")
GEOPOSE = ("The pose as an OGC GeoPose 1.0 Basic-Quaternion: position (lat, lon, h = "
           "altitude_m) and quaternion (x, y, z, w), the rotation of the local "
           "East-North-Up frame about Up by the heading (yaw = 90 deg - heading_deg); the "
           "localiser estimates no pitch or roll, so none is applied. quaternion is null "
           "when the heading is unknown; geopose is null when the altitude is, since "
           "GeoPose Basic needs a height and none is made up")


class PoseFields(BaseModel):
    """What a pose says of where the camera is: a session's estimate
    (:class:`PoseEstimate`) and a single image's
    (:class:`~vloc.app.localize.schemas.Localization`).

    The fields are declared here once: the table ``pose_estimates`` is generated from them
    (:mod:`app.sessions.pose`), and an estimate's fields of the same name are copied into
    them, so a new field of the core's estimate is added in this class only.
    """

    map_id: uuid.UUID = Field(description="The map localised against")
    map_revision: int = Field(description="Its packed revision that gave the estimate (a "
                                          "session following its map moves to a new "
                                          "revision between two frames)")
    status: Status = Field(
        description="initialising (no converged estimate yet, since the start or a reset), "
                    "tracking, or lost (the estimate spread out after converging)")
    converged: bool = Field(description="Tracking with ``horizontal_accuracy_m`` within the "
                                        "server's bound (VLOC_CONVERGED_ACCURACY_M)")
    x: float = Field(description="East, metres in the map's local frame")
    y: float = Field(description="North, metres in the map's local frame")
    lat: float = Field(description="WGS84 latitude, degrees")
    lon: float = Field(description="WGS84 longitude, degrees")
    altitude_m: float | None = Field(
        description="Altitude in metres as the device reported it with the frame "
                    "(``altitude_m``); null when it did not: the localiser estimates none")
    horizontal_accuracy_m: float = Field(
        description="Radius in metres of the circle about (lat, lon) that holds the "
                    "position with 68 % probability, from ``cov``")
    heading_deg: float | None = Field(
        description="Compass bearing of the frame's top edge, degrees clockwise from north; "
                    "null when unknown")
    heading_sigma_deg: float | None = Field(description="Its standard deviation, degrees")
    heading_source: Literal["geometry", "device"] | None = Field(
        description="geometry: solved against the map's camera geometry this "
                                   "step; device: the frame's own heading, reported back "
                                   "when the step solved none; null with no heading")
    sigma_x: float = Field(description="Standard deviation east, metres")
    sigma_y: float = Field(description="Standard deviation north, metres")
    cov: list[float] = Field(min_length=4, max_length=4,
                             description="Row-major 2x2 position covariance, m^2")
    feature: str = Field(max_length=32, description=FEATURE)
    next_feature: str = Field(max_length=32, description=NEXT_FEATURE)
    measurement: str = Field("", max_length=64, description=MEASUREMENT)
    metadata_used: str = Field(
        "", max_length=64, description="Which of the frame's metadata the step used (heading, "
                                   "gps, altitude, velocity, joined by +); empty for none")
    gps_gate: Literal["", "used", "rejected"] = Field(
        "", description="Empty when the frame carried no GPS fix; used: fused; "
                                   "rejected: ignored for disagreeing with the images")
    n_particles: int = Field(description="Particles of the filter; 0 for localisers "
                                         "without")
    image_id: int | None = Field(description="The map image that matched best this step "
                                             "(its id under /v1/maps/{id}/images); null "
                                             "when none")
    image_filename: str | None = Field(max_length=255, description="Its file name")
    decode_ms: float = Field(description="Decoding and resizing the frame in the worker")
    processing_ms: float = Field(description="The core's step time")
    cloud: list[tuple[float, float]] = Field(
        default_factory=list, max_length=1000,
        description="On the stream only (not stored): a sample of up to 64 particles, "
                    "[[x, y], ...] in metres, drawn in proportion to their weights")

    @computed_field(description=GEOPOSE)
    @property
    def geopose(self) -> GeoPose | None:
        if self.altitude_m is None:  # GeoPose Basic needs a height; none is made up
            return None
        return GeoPose(position=GeoPosePosition(lat=self.lat, lon=self.lon,
                                                h=self.altitude_m),
                       quaternion=None if self.heading_deg is None
                       else heading_quaternion(self.heading_deg))


class PoseEstimate(PoseFields):
    """One estimate of a session, as stored, returned and streamed (``type: "pose"``)."""

    type: Literal["pose"] = "pose"
    session_id: uuid.UUID
    seq: int
    captured_at: datetime | None
    received_at: datetime
    latency_ms: float = Field(description="Frame arrival to estimate back in the API")
    navigation: NavigationState | None = Field(
        None, description="For a session that follows a route; null otherwise")


def heading_quaternion(heading_deg: float) -> Quaternion:
    """The ENU-frame rotation about Up of a compass heading (clockwise from north): yaw,
    counter-clockwise from east, is 90 deg - heading."""
    half = math.radians(90.0 - heading_deg) / 2.0
    return Quaternion(x=0.0, y=0.0, z=math.sin(half), w=math.cos(half))


class FrameError(BaseModel):
    """A frame that was accepted but gave no estimate (``type: "frame_error"``)."""

    type: Literal["frame_error"] = "frame_error"
    session_id: uuid.UUID
    seq: int
    captured_at: datetime | None
    kind: str = Field(description="bad_image, error, not_open, worker_died, not_stored or "
                                  "interrupted")
    reason: str
    latency_ms: float | None = Field(
        description="Frame arrival to its failure back in the API; null when interrupted")


class NavigationRead(BaseModel):
    """The route a session follows."""

    route_id: uuid.UUID
    params: dict[str, Any]
    nodes: list[int] = Field(description="First and last route node followed")
    points: int = Field(description="Taught path points followed")


class SessionRead(BaseModel):
    id: uuid.UUID
    map_id: uuid.UUID
    map_revision: int = Field(description="The map revision the session localises "
                                          "against now")
    follows_map: bool = Field(description="Whether it moves to the map's new revision when "
                                          "the map is rebuilt or restored")
    mode: Literal[MODES]
    params: dict[str, Any]
    seed: int
    created_at: datetime
    last_seq: int | None = Field(description="Highest sequence number processed")
    frames_processed: int
    frames_failed: int
    frames_pending: int
    stats: SessionStats
    last_pose: PoseEstimate | None
    state: Literal["active", "expired"] = Field(
        description="active, or expired once idle for ttl_s: frames and controls then get "
                    "410 session-expired; poses stay readable")
    ttl_s: int = Field(description="Seconds of inactivity after which the session expires")
    last_active_at: datetime = Field(description="The last frame or keep-alive")
    expires_at: datetime = Field(description="When it expires without further activity")
    navigation: NavigationRead | None = None


class SessionCreated(SessionRead):
    token: str = Field(description="Shown once: the bearer token for frames and the stream")


class FrameAccepted(BaseModel):
    seq: int


class InitialPose(BaseModel):
    """A position prior: ``lat``/``lon`` (WGS84) or ``x``/``y`` (map frame, metres).

    The position must lie within the map's extent plus a margin
    (:data:`app.sessions.service.INITIAL_POSE_MARGIN_M`); that is checked against the
    session's map revision.
    """

    model_config = ConfigDict(strict=True, extra="forbid", allow_inf_nan=False)

    lat: float | None = Field(None, ge=-90, le=90)
    lon: float | None = Field(None, ge=-180, le=180)
    x: float | None = Field(None, ge=-1e7, le=1e7, description="East, metres")
    y: float | None = Field(None, ge=-1e7, le=1e7, description="North, metres")
    sigma: float = Field(5.0, gt=0, le=MAX_INITIAL_SIGMA_M,
                         description="Standard deviation, metres")
    heading_deg: float | None = Field(
        None, ge=0, lt=360, description="Compass bearing of the camera's top edge, degrees "
                                        "clockwise from north; only for a localiser that "
                                        "keeps a heading (422 bad-control otherwise)")
    heading_sigma_deg: float | None = Field(None, gt=0, le=180,
                                            description="Its standard deviation, degrees")

    @model_validator(mode="after")
    def _one_pair(self) -> InitialPose:
        geo = self.lat is not None or self.lon is not None
        local = self.x is not None or self.y is not None
        if geo == local:
            raise ValueError("give either lat and lon, or x and y")
        pair = (self.lat, self.lon) if geo else (self.x, self.y)
        if any(v is None or not math.isfinite(v) for v in pair):
            raise ValueError("both coordinates are needed, as finite numbers")
        if self.heading_sigma_deg is not None and self.heading_deg is None:
            raise ValueError("heading_sigma_deg needs heading_deg")
        return self
