"""What the client returns: typed, read-only views of the server's JSON.

Unknown members are ignored, so a newer server with more fields does not break an older
client; ids are strings (UUIDs) and times are timezone-aware :class:`datetime` objects.
"""

from __future__ import annotations

from datetime import datetime
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator


class _Model(BaseModel):
    model_config = ConfigDict(extra="ignore", frozen=True)


def _str_id(value: Any) -> Any:
    return str(value) if value is not None else None


class GeoExtent(_Model):
    """Bounding box of the map's images, WGS84 degrees."""

    min_lat: float
    min_lon: float
    max_lat: float
    max_lon: float


class LocalExtent(_Model):
    """Bounding box of the built images in the map's east-north frame, metres."""

    min_east: float
    min_north: float
    max_east: float
    max_north: float


class Origin(_Model):
    """WGS84 origin of the map's local frame."""

    lat: float
    lon: float
    alt: float = 0.0


class FlightSelfCheck(_Model):
    """The self-check's figures over one of the map's flights."""

    flight: int = Field(description="numbered from 0 in the order flown")
    name: str | None = Field(None, description="as the upload named it")
    images: int
    registered: float
    mean_m: float | None = None
    median_m: float | None = None
    within_5m: float | None = None


class MapSelfCheck(_Model):
    """The map's own images localised against the rest of it at build time."""

    images: int
    registered: float
    mean_m: float | None = None
    median_m: float | None = Field(None, description="the map localises to about this (m)")
    within_5m: float | None = None
    floor_median_m: float
    trusted: bool
    flights: list[FlightSelfCheck] | None = Field(
        None, description="the same per flight, for a map of several")


class MapGeometry(_Model):
    """The current revision's camera geometry and what the map measured of itself."""

    status: str = Field(description="accepted, refused or none")
    reason: str | None = None
    images: int
    placed: int | None = None
    models: int | None = None
    focal_px: float | None = None
    residual_px: float | None = None
    gps_rms_m: float | None = None
    gps_rms_vertical_m: float | None = None
    self_check: MapSelfCheck | None = None


class Map(_Model):
    """A map: its images, build state, local frame and camera geometry."""

    id: str
    name: str
    status: str = Field(description="empty, unbuilt, building, ready or failed")
    revision: int
    image_count: int
    pending_images: int = 0
    extent: GeoExtent | None = None
    local_extent: LocalExtent | None = None
    origin: Origin | None = None
    created_at: datetime | None = None
    built_at: datetime | None = None
    last_job_id: str | None = None
    geometry: MapGeometry | None = None

    _ids = field_validator("id", "last_job_id", mode="before")(_str_id)


class MapRevision(_Model):
    """One packed revision of a map: what it holds and what changed since the revision it
    was built on."""

    revision: int
    current: bool
    built_at: datetime | None = None
    job_id: str | None = None
    base_revision: int = 0
    image_count: int = 0
    added: int = 0
    removed: int = 0
    active_sessions: int = 0
    disk_bytes: int | None = None
    shared_bytes: int | None = None
    vocabularies_from: int | None = Field(
        None, description="the revision that trained its place vocabularies (an earlier "
                          "one where an update kept them)")
    dropped_at: datetime | None = None
    geometry: MapGeometry | None = None

    _ids = field_validator("job_id", mode="before")(_str_id)


class MapImage(_Model):
    """One image of a map, as the server stored it."""

    id: int
    filename: str
    lat: float
    lon: float
    alt: float | None = None
    east: float | None = None
    north: float | None = None
    width: int = 0
    height: int = 0
    byte_size: int = 0
    content_type: str = ""
    file_hash: str = ""
    captured_at: datetime | None = None
    flight: str | None = None
    """The flight (or pass) it was uploaded as part of, where the upload named one."""
    position_source: str = ""
    built_revision: int | None = None


class ImageRejection(_Model):
    """A file of an upload that was not added, with the status it alone would have got."""

    filename: str
    status: int
    reason: str = Field(description="too-large, bad-image, no-gps, duplicate...")
    detail: str = ""


class UploadResult(_Model):
    """Per-file outcome of an image upload."""

    accepted: list[MapImage] = Field(default_factory=list)
    rejected: list[ImageRejection] = Field(default_factory=list)


class Job(_Model):
    """A background map build."""

    id: str
    map_id: str | None = None
    status: str = Field(description="queued, running, done or failed")
    progress: float = 0.0
    stage: str | None = Field(None, description="what the build is doing now")
    error: str | None = None
    n_images: int = 0
    n_extracted: int = 0
    revision: int | None = None
    full: bool = Field(False, description="whether the build is whole (nothing carried over "
                                          "from the revision before)")
    created_at: datetime | None = None
    started_at: datetime | None = None
    finished_at: datetime | None = None

    _ids = field_validator("id", "map_id", mode="before")(_str_id)

    @property
    def finished(self) -> bool:
        return self.status in ("done", "failed")


class Quaternion(_Model):
    x: float
    y: float
    z: float
    w: float


class GeoPosePosition(_Model):
    lat: float
    lon: float
    h: float


class GeoPose(_Model):
    """OGC GeoPose 1.0 Basic-Quaternion: position, and orientation in the local
    East-North-Up frame (None when the heading is unknown). A pose without an altitude has
    no GeoPose (``Pose.geopose`` is None)."""

    position: GeoPosePosition
    quaternion: Quaternion | None = None


class PoseFields(_Model):
    """Where the camera is: the fields a session's :class:`Pose` and a single image's
    :class:`Localization` share. docs/api.md describes every one."""

    map_id: str = ""
    map_revision: int = 0
    captured_at: datetime | None = None
    status: Literal["initialising", "tracking", "lost"]
    converged: bool = False
    x: float
    y: float
    lat: float
    lon: float
    altitude_m: float | None = None
    horizontal_accuracy_m: float | None = None
    """None only from a server older than this field."""
    heading_deg: float | None = None
    heading_sigma_deg: float | None = None
    heading_source: Literal["geometry", "device"] | None = None
    sigma_x: float
    sigma_y: float
    cov: tuple[float, float, float, float]
    feature: str
    next_feature: str = ""
    measurement: str = ""
    metadata_used: str = ""
    gps_gate: Literal["", "used", "rejected"] = ""
    n_particles: int = 0
    image_id: int | None = None
    image_filename: str | None = None
    decode_ms: float = 0.0
    processing_ms: float = 0.0
    latency_ms: float = 0.0
    cloud: list[tuple[float, float]] = []
    geopose: GeoPose | None = None

    _map_id = field_validator("map_id", mode="before")(_str_id)


class Pose(PoseFields):
    """One estimate of a session (stream message ``type: "pose"``).

    ``x``/``y`` are east/north metres in the map's frame; ``cov`` is the row-major 2x2
    position covariance in m^2 and ``horizontal_accuracy_m`` the radius of its 68 % circle;
    ``heading_deg`` is None where the localiser knows no heading; ``image_id`` and
    ``image_filename`` name the map image that matched best. ``decode_ms`` and
    ``processing_ms`` are the worker's decoding and the core's step time, ``latency_ms``
    the time from the frame's arrival to its estimate.
    """

    type: Literal["pose"] = "pose"
    session_id: str = ""
    seq: int
    received_at: datetime | None = None
    navigation: dict[str, Any] | None = Field(
        None, description="Path following, for a session that follows a route: state (EKF "
                          "x, y, theta, v, omega), command (v, omega), reference, cross_track, "
                          "heading_error, node, progress, length, arrived")

    _ids = field_validator("session_id", mode="before")(_str_id)


class Localization(PoseFields):
    """Where a single image was taken (:meth:`Client.localize`)."""

    type: Literal["localization"] = "localization"


class Coverage(_Model):
    """A built map near a position (:meth:`Client.coverage`)."""

    map_id: str
    name: str
    revision: int
    distance_m: float
    image_count: int

    _ids = field_validator("map_id", mode="before")(_str_id)


class FrameError(_Model):
    """An accepted frame that gave no estimate (stream message ``type: "frame_error"``)."""

    type: Literal["frame_error"] = "frame_error"
    session_id: str = ""
    seq: int
    captured_at: datetime | None = None
    kind: str = Field(description="bad_image, error, not_open, worker_died, not_stored or "
                                  "interrupted")
    reason: str = ""
    latency_ms: float | None = Field(0.0, description="None for an interrupted frame")

    _ids = field_validator("session_id", mode="before")(_str_id)


class SessionStats(_Model):
    sift_share: float | None = None
    latency_ms_p50: float | None = None
    latency_ms_p99: float | None = None
    processing_ms_mean: float | None = None


class Session(_Model):
    """A localisation session. ``token`` is set only on the value :meth:`create_session`
    returns: the server shows it once."""

    id: str
    map_id: str
    map_revision: int = 0
    """The map revision the session localises against now."""
    follows_map: bool | None = None
    """Whether it moves to the map's new revisions; None from a server older than this
    field."""
    mode: str
    params: dict[str, Any] = Field(default_factory=dict)
    seed: int | None = None
    created_at: datetime | None = None
    last_seq: int | None = None
    frames_processed: int = 0
    frames_failed: int = 0
    frames_pending: int = 0
    stats: SessionStats = Field(default_factory=SessionStats)
    last_pose: Pose | None = None
    state: Literal["active", "expired"] = "active"
    ttl_s: int | None = None
    last_active_at: datetime | None = None
    expires_at: datetime | None = None
    navigation: dict[str, Any] | None = None
    token: str | None = None

    _ids = field_validator("id", "map_id", mode="before")(_str_id)


class FrameAccepted(_Model):
    """A frame queued for processing: its sequence number."""

    seq: int


StreamMessage = Pose | FrameError
"""What the pose stream yields."""


def parse_message(data: dict[str, Any]) -> StreamMessage | dict[str, Any]:
    """A stream message as a model; control messages (``closed``...) stay dicts."""
    kind = data.get("type")
    if kind == "pose":
        return Pose.model_validate(data)
    if kind == "frame_error":
        return FrameError.model_validate(data)
    return data


class Route(_Model):
    """A taught route of a map: its images in driving order with odometry, partitioned into
    topological nodes and relaxed. ``nodes``, ``arcs`` and ``images`` (the taught path) are
    filled in by :meth:`Client.get_route`."""

    id: str
    map_id: str
    name: str
    status: str = Field(description="building, ready or failed")
    error: str | None = None
    params: dict[str, Any] = Field(default_factory=dict)
    n_images: int = 0
    n_nodes: int | None = None
    n_loops: int | None = None
    length_m: float | None = None
    sweeps: int | None = None
    nodes: list[dict[str, Any]] = Field(default_factory=list)
    arcs: list[dict[str, Any]] = Field(default_factory=list)
    images: list[dict[str, Any]] = Field(default_factory=list)

    _ids = field_validator("id", "map_id", mode="before")(_str_id)
