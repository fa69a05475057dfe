"""Bodies of the session routes and the messages of the pose stream."""

from __future__ import annotations

import math
import uuid
from datetime import datetime
from typing import Annotated, Any, Literal

from pydantic import BaseModel, Field, model_validator

MAX_SEQ = 2**63 - 1
"""The largest frame sequence number: the database stores it as a signed 64-bit integer."""

Seq = Annotated[int, Field(ge=0, le=MAX_SEQ, strict=True,
                           description=f"Frame sequence number, 0 to {MAX_SEQ}")]


class SessionCreate(BaseModel):
    map_id: uuid.UUID
    mode: str = Field("hybrid", description="hybrid, global, sift, hierarchical or retrieval")
    params: dict[str, Any] = Field(default_factory=dict,
                                   description="Localiser parameters; defaults filled in")
    seed: int | None = Field(None, ge=0, lt=2**63,
                             description="Random seed (or params.seed); random when unset")


class SessionStats(BaseModel):
    sift_share: float | None = Field(description="Share of estimates that used SIFT")
    latency_ms_p50: float | None
    latency_ms_p99: float | None
    processing_ms_mean: float | None


class PoseEstimate(BaseModel):
    """One estimate, as stored and as streamed (``type: "pose"``)."""

    type: Literal["pose"] = "pose"
    session_id: uuid.UUID
    seq: int
    captured_at: datetime | None
    received_at: datetime
    x: float = Field(description="East, metres in the map's local frame")
    y: float = Field(description="North, metres in the map's local frame")
    lat: float
    lon: float
    sigma_x: float
    sigma_y: float
    cov: list[float] = Field(min_length=4, max_length=4,
                             description="Row-major 2x2 position covariance, m^2")
    feature: str = Field(description="Feature type this step used")
    next_feature: str
    n_particles: int
    status: str = Field(description="initialising, tracking or lost")
    best_image: int
    decode_ms: float = Field(description="Decoding and resizing the frame in the worker")
    processing_ms: float = Field(description="The core's step time")
    latency_ms: float = Field(description="Frame arrival to estimate back in the API")


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


class SessionRead(BaseModel):
    id: uuid.UUID
    map_id: uuid.UUID
    map_revision: int
    mode: str
    params: dict[str, Any]
    seed: int
    created_at: datetime
    last_seq: int | None = Field(description="Highest sequence number processed")
    frames_processed: int
    frames_failed: int
    frames_pending: int
    stats: SessionStats
    last_pose: PoseEstimate | None


class SessionCreated(SessionRead):
    token: str = Field(description="Shown once: the bearer token for frames and the stream")


class FrameAccepted(BaseModel):
    seq: int


class InitialPose(BaseModel):
    """A position prior: ``lat``/``lon`` (WGS84) or ``x``/``y`` (map frame, metres)."""

    lat: float | None = None
    lon: float | None = None
    x: float | None = None
    y: float | None = None
    sigma: float = Field(5.0, gt=0, le=1e5, description="Standard deviation, metres")

    @model_validator(mode="after")
    def _one_pair(self) -> InitialPose:
        geo = self.lat is not None or self.lon is not None
        local = self.x is not None or self.y is not None
        if geo == local:
            raise ValueError("give either lat and lon, or x and y")
        pair = (self.lat, self.lon) if geo else (self.x, self.y)
        if any(v is None or not math.isfinite(v) for v in pair):
            raise ValueError("both coordinates are needed, as finite numbers")
        return self
