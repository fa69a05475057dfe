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


class Map(_Model):
    """A map: its images, build state and local frame."""

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

    _ids = field_validator("id", "last_job_id", mode="before")(_str_id)


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
    error: str | None = None
    n_images: int = 0
    n_extracted: int = 0
    revision: int | None = None
    created_at: datetime | None = None
    started_at: datetime | None = None
    finished_at: datetime | None = None

    _ids = field_validator("id", "map_id", mode="before")(_str_id)

    @property
    def finished(self) -> bool:
        return self.status in ("done", "failed")


class Pose(_Model):
    """One estimate of a session (stream message ``type: "pose"``).

    ``x``/``y`` are east/north metres in the map's frame; ``cov`` is the row-major 2x2
    position covariance in m^2; ``processing_ms`` is the core's step time and
    ``latency_ms`` the time from the frame's arrival to its estimate.
    """

    type: Literal["pose"] = "pose"
    session_id: str = ""
    seq: int
    captured_at: datetime | None = None
    received_at: datetime | None = None
    x: float
    y: float
    lat: float
    lon: float
    sigma_x: float
    sigma_y: float
    cov: tuple[float, float, float, float]
    feature: str
    next_feature: str = ""
    n_particles: int = 0
    status: str = ""
    best_image: int = -1
    processing_ms: float = 0.0
    latency_ms: float = 0.0

    _ids = field_validator("session_id", mode="before")(_str_id)


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
