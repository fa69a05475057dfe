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


class FlightSelfCheck(BaseModel):
    """The self-check's figures over the images of one of the map's flights."""

    flight: int = Field(description="The flight, numbered from 0 in the order flown")
    name: str | None = Field(None, description="Its name, where the upload named it")
    images: int = Field(description="Its images localised by the check")
    registered: float = Field(description="Share of them the geometry placed at all")
    mean_m: float | None = Field(None, description="Mean distance of those placed from "
                                                   "their GPS (m)")
    median_m: float | None = Field(None, description="Their median distance (m)")
    within_5m: float | None = Field(None, description="Share placed within 5 m")


class MapSelfCheck(BaseModel):
    """The map's own images localised against the rest of it at build time, compared with
    their GPS: how well frames can expect to be placed."""

    images: int = Field(description="Map images localised by the check")
    registered: float = Field(description="Share of them the geometry placed at all")
    mean_m: float | None = Field(None, description="Mean distance of those placed from "
                                                   "their GPS (m)")
    median_m: float | None = Field(None, description="Median distance (m): the map "
                                                     "localises to about this")
    within_5m: float | None = Field(None, description="Share placed within 5 m")
    floor_median_m: float | None = Field(description="Median distance of the checked images from "
                                              "their nearest other map image (m): the best "
                                              "a position from the map's images alone does")
    trusted: bool = Field(description="Whether frames' fixes use the geometry: it beats "
                                      "the nearest-image floor")
    every_image_mean_m: float | None = Field(
        None, description="Mean over every map image, the ones no pose reaches counted at "
                          "their nearest-image distance (m): what to expect of the map as a "
                          "whole, holes included")
    every_image_median_m: float | None = Field(None, description="Their median (m)")
    every_image_within_5m: float | None = Field(None, description="Their share within 5 m")
    flights: list[FlightSelfCheck] | None = Field(
        None, description="The same figures per flight, for a map of several flights "
                          "(named at upload, or apart in time by more than 30 minutes)")


class MapGeometryRead(BaseModel):
    """The current revision's camera geometry (structure from motion, COLMAP)."""

    status: Literal["accepted", "refused", "none"] = Field(
        description="accepted (frames get metric fixes from it), refused (reconstructed, "
                    "but its self-check did no better than the nearest image) or none (no "
                    "structure could be recovered)")
    reason: str | None = Field(None, description="Why the map has no geometry")
    images: int
    placed: int | None = Field(None, description="Map images whose camera was placed")
    models: int | None = Field(None, description="Separate reconstructions they come from")
    focal_px: float | None = Field(None, description="Focal length at 320x240 (px)")
    residual_px: float | None = Field(None, description="Mean reprojection error (px at "
                                                        "320x240)")
    gps_rms_m: float | None = Field(None, description="RMS horizontal distance of the placed "
                                                      "cameras from their GPS (m)")
    gps_rms_vertical_m: float | None = None
    self_check: MapSelfCheck | None = None


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
    geometry: MapGeometryRead | None = Field(
        None, description="The current revision's camera geometry; null before the first "
                          "build (or for a map built before maps reported it)")


class RevisionRead(BaseModel):
    """One packed revision of a map."""

    revision: int
    current: bool = Field(description="Whether new sessions and single-image localisations "
                                      "use it")
    built_at: datetime
    job_id: uuid.UUID | None = Field(description="The build that packed it (null for a "
                                                 "revision recorded from an older server)")
    base_revision: int = Field(description="The revision it was built on: what added and "
                                           "removed compare with (0 for the first)")
    image_count: int
    added: int = Field(description="Images it holds that its base revision did not")
    removed: int = Field(description="Images its base revision held that it does not")
    active_sessions: int = Field(description="Active sessions localising against it")
    disk_bytes: int | None = Field(description="Size of its packed files; null where they "
                                               "are missing or dropped")
    shared_bytes: int | None = Field(
        None, description="Of disk_bytes, the files it shares with other revisions of the "
                          "map (an update keeps the unchanged images' features in the same "
                          "files): dropping it frees disk_bytes less these at most; null "
                          "where its files are missing or dropped")
    vocabularies_from: int | None = Field(
        None, description="The revision that trained its place vocabularies: itself where "
                          "its build trained them, an earlier one where an update kept "
                          "them; null where its files are missing or dropped, or it was "
                          "packed before this was recorded")
    dropped_at: datetime | None = Field(description="When it was dropped with its files; "
                                                    "its number is never packed again")
    geometry: MapGeometryRead | None = Field(
        None, description="Its camera geometry and self-check, as the map showed them while "
                          "it was current")


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
    flight: str | None = Field(description="The flight (or pass) the image was uploaded as "
                                           "part of; null where the upload named none")
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
