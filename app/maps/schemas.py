"""Request and response bodies of the maps routes."""

from __future__ import annotations

import uuid
from datetime import datetime
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class MapCreate(BaseModel):
    name: str = Field(min_length=1, max_length=200, pattern=r"^[^\x00-\x1f\x7f]+$",
                      description="Any text without control characters (NUL, newlines...)")


class GeoExtent(BaseModel):
    """Bounding box of the map images in WGS84 degrees."""

    min_lat: float
    min_lon: float
    max_lat: float
    max_lon: float


class LocalExtent(BaseModel):
    """Bounding box of the built map images in the map's east-north frame, metres."""

    min_east: float
    min_north: float
    max_east: float
    max_north: float


class Origin(BaseModel):
    lat: float
    lon: float
    alt: float


class MapRead(BaseModel):
    id: uuid.UUID
    name: str
    status: Literal["empty", "unbuilt", "building", "ready", "failed"] = Field(
        description="empty (no images), unbuilt (images waiting for a build), building, "
                    "ready (the current revision holds every image) or failed (the last "
                    "build failed; an earlier revision may still serve)")
    revision: int = Field(description="0 until the first build; bumped by every build")
    image_count: int
    pending_images: int = Field(description="Images not yet in a built revision")
    extent: GeoExtent | None
    local_extent: LocalExtent | None
    origin: Origin | None = Field(description="Origin of the current revision's local frame")
    created_at: datetime
    built_at: datetime | None
    last_job_id: uuid.UUID | None


class MapImageRead(BaseModel):
    model_config = ConfigDict(from_attributes=True)

    id: int
    filename: str
    file_hash: str
    content_type: str
    byte_size: int
    width: int
    height: int
    lat: float
    lon: float
    alt: float | None
    east: float | None
    north: float | None
    captured_at: datetime | None
    position_source: str
    built_revision: int | None


class ImageRejection(BaseModel):
    filename: str
    status: int = Field(description="The HTTP status this file alone would get")
    reason: str = Field(description="Stable slug: too-large, bad-image, no-gps, duplicate...")
    detail: str


class ImageUploadResult(BaseModel):
    accepted: list[MapImageRead]
    rejected: list[ImageRejection]


class BuildAccepted(BaseModel):
    job_id: uuid.UUID
    status: Literal["queued", "running", "done", "failed"]
