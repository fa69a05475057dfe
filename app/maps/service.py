"""Maps and their images: create, read, delete, add images (validated, deduplicated)."""

from __future__ import annotations

import asyncio
import hashlib
import os
import shutil
import uuid
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

from sqlalchemy import func, select
from sqlalchemy.orm import Session, sessionmaker

from vloc.app.config import Settings
from vloc.app.imagecheck import ImageHeader, check_image
from vloc.app.jobs.models import BuildJob, JobStatus
from vloc.app.maps.models import Map, MapImage, MapStatus
from vloc.app.maps.schemas import (
    GeoExtent,
    ImageRejection,
    ImageUploadResult,
    LocalExtent,
    MapImageRead,
    MapRead,
    Origin,
)
from vloc.app.problems import Problem, ProblemKind, not_found
from vloc.app.sessions.models import LocalisationSession
from vloc.app.validation import (
    MAX_ALT_M,
    MIN_ALT_M,
    aware,
    check_captured_at,
    check_position,
    plausible_time,
)


@dataclass(frozen=True, slots=True)
class Upload:
    """One uploaded file as received."""

    filename: str
    data: bytes


@dataclass(frozen=True, slots=True)
class GivenPosition:
    """A position given with a single-file upload instead of EXIF GPS."""

    lat: float
    lon: float
    alt: float | None = None
    captured_at: datetime | None = None


Verifier = Callable[[list[bytes]], Awaitable[list[str | None]]]
"""Decodes images fully (in the workers): one error message or None per image."""


def create_map(db: Session, *, name: str) -> Map:
    m = Map(name=name, status=MapStatus.EMPTY, revision=0)
    db.add(m)
    db.commit()
    return m


def list_maps(db: Session, *, limit: int | None = None, offset: int = 0) -> list[MapRead]:
    query = select(Map).order_by(Map.created_at, Map.id).offset(offset).limit(limit)
    return [read_map(db, map_=m) for m in db.scalars(query)]


def read_map(db: Session, *, map_: Map) -> MapRead:
    count, pending, lat0, lon0, lat1, lon1 = db.execute(
        select(func.count(MapImage.id),
               func.count(MapImage.id).filter(MapImage.built_revision.is_(None)),
               func.min(MapImage.lat), func.min(MapImage.lon),
               func.max(MapImage.lat), func.max(MapImage.lon))
        .where(MapImage.map_id == map_.id)).one()
    e0, n0, e1, n1 = db.execute(
        select(func.min(MapImage.east), func.min(MapImage.north),
               func.max(MapImage.east), func.max(MapImage.north))
        .where(MapImage.map_id == map_.id, MapImage.built_revision.is_not(None))).one()
    last_job = db.scalar(select(BuildJob.id).where(BuildJob.map_id == map_.id)
                         .order_by(BuildJob.created_at.desc()).limit(1))
    origin = None
    if map_.origin_lat is not None:
        origin = Origin(lat=map_.origin_lat, lon=map_.origin_lon, alt=map_.origin_alt or 0.0)
    return MapRead(
        id=map_.id, name=map_.name, status=map_.status, revision=map_.revision,
        image_count=count, pending_images=pending,
        extent=GeoExtent(min_lat=lat0, min_lon=lon0, max_lat=lat1, max_lon=lon1)
        if count else None,
        local_extent=LocalExtent(min_east=e0, min_north=n0, max_east=e1, max_north=n1)
        if e0 is not None else None,
        origin=origin, created_at=map_.created_at, built_at=map_.built_at,
        last_job_id=last_job, geometry=map_.geometry)


def refuse_while_building(db: Session, map_: Map) -> None:
    """409 ``map-busy`` while a build of the map is queued or running."""
    if db.scalar(select(func.count(BuildJob.id)).where(
            BuildJob.map_id == map_.id, BuildJob.status.in_(JobStatus.ACTIVE))):
        raise Problem(409, "a build of this map is running", kind=ProblemKind.MAP_BUSY)


def delete_map(db: Session, *, map_: Map, settings: Settings) -> None:
    """Delete a map with its images, features, jobs and packed revisions.

    Refused (409) while a build runs or sessions use the map.
    """
    refuse_while_building(db, map_)
    sessions = db.scalar(select(func.count(LocalisationSession.id))
                         .where(LocalisationSession.map_id == map_.id))
    if sessions:
        raise Problem(409, f"{sessions} session(s) use this map; delete them first",
                      kind=ProblemKind.MAP_IN_USE, sessions=sessions)
    map_id = str(map_.id)
    db.delete(map_)
    db.commit()
    shutil.rmtree(settings.data_dir / "maps" / map_id, ignore_errors=True)


def delete_image(db: Session, *, map_: Map, image_id: int, settings: Settings) -> None:
    """Delete one image of a map with its features and file.

    The map then needs a build to leave the image out of a revision (``unbuilt``), or has
    no images left (``empty``). Revisions already packed, and the sessions on them, keep
    the image. Refused (409) while a build runs: the build may be reading it.
    """
    image = get_image(db, map_=map_, image_id=image_id)
    refuse_while_building(db, map_)
    path = image_path(settings, image)
    db.delete(image)
    db.flush()
    remaining = db.scalar(select(func.count(MapImage.id)).where(MapImage.map_id == map_.id))
    map_.status = MapStatus.UNBUILT if remaining else MapStatus.EMPTY
    db.commit()
    path.unlink(missing_ok=True)


def get_image(db: Session, *, map_: Map, image_id: int) -> MapImage:
    """One image of the map; 404 for an image of another map or none."""
    image = db.get(MapImage, image_id)
    if image is None or image.map_id != map_.id:
        raise not_found("image", image_id)
    return image


def list_images(db: Session, *, map_: Map, limit: int | None = None,
                after_id: int = 0) -> list[MapImage]:
    return list(db.scalars(select(MapImage).where(MapImage.map_id == map_.id,
                                                  MapImage.id > after_id)
                           .order_by(MapImage.id).limit(limit)))


async def add_images(*, db_sessions: sessionmaker[Session], map_id: uuid.UUID,
                     uploads: Sequence[Upload], position: GivenPosition | None,
                     settings: Settings, verify: Verifier,
                     flight: str | None = None) -> ImageUploadResult:
    """Validate, store and register uploaded map images (of the flight ``flight`` names,
    where given).

    Every file is checked on its own (size, header, GPS, duplicate, full decode in the
    workers); the good ones are stored, the others reported with the reason. When no file
    is good, nothing is stored and a problem is raised with the reasons. The database work
    runs in threads, each with its own short session, so that no connection is held while
    the workers decode.
    """
    if not uploads:
        raise Problem(422, "no files in the upload (form field 'files')", kind=ProblemKind.NO_FILES)
    if len(uploads) > settings.max_files_per_upload:
        raise Problem(413, f"{len(uploads)} files exceed the limit of "
                      f"{settings.max_files_per_upload} per upload", kind=ProblemKind.TOO_MANY_FILES)
    if flight is not None:
        flight = flight.strip()
        if not flight:
            raise Problem(422, "flight is blank; name the flight, or leave the field out",
                          kind=ProblemKind.BAD_TEXT, field="flight")
    if position is not None:
        if len(uploads) != 1:
            raise Problem(422, "lat/lon form fields apply to a single file; upload several "
                          "files with EXIF GPS instead", kind=ProblemKind.POSITION_AMBIGUOUS)
        check_position(position.lat, position.lon, position.alt)
        check_captured_at(position.captured_at)
    rejected, candidates = await asyncio.to_thread(
        _screen, db_sessions, map_id, uploads, position, settings)
    errors = await verify([c[0].data for c in candidates]) if candidates else []
    good = []
    for cand, error in zip(candidates, errors, strict=True):
        if error is None:
            good.append(cand)
        else:
            rejected.append(ImageRejection(filename=cand[0].filename, status=422,
                                           reason=ProblemKind.BAD_IMAGE, detail=error))
    if not good:
        statuses = {r.status for r in rejected}
        status = statuses.pop() if len(statuses) == 1 else 422
        raise Problem(status, "no image was accepted: " + "; ".join(
            f"{r.filename}: {r.detail}" for r in rejected), kind=ProblemKind.NO_IMAGE_ACCEPTED,
            rejected=[r.model_dump() for r in rejected])
    accepted = await asyncio.to_thread(_store, db_sessions, map_id, good, settings, flight)
    return ImageUploadResult(accepted=accepted, rejected=rejected)


def _screen(db_sessions: sessionmaker[Session], map_id: uuid.UUID, uploads: Sequence[Upload],
            position: GivenPosition | None, settings: Settings) -> tuple[list, list]:
    """Header, GPS and duplicate checks: (rejections, candidates for the full decode)."""
    with db_sessions() as db:
        if db.get(Map, map_id) is None:
            raise not_found("map", map_id)
        existing = set(db.scalars(select(MapImage.file_hash).where(MapImage.map_id == map_id)))
    rejected: list[ImageRejection] = []
    candidates: list[tuple[Upload, ImageHeader, GivenPosition, str, str]] = []
    for up in uploads:
        try:
            header, pos = _check_one(up, position, settings)
        except Problem as p:
            rejected.append(ImageRejection(filename=up.filename, status=p.status,
                                           reason=p.kind or ProblemKind.BAD_REQUEST, detail=p.detail))
            continue
        digest = hashlib.sha256(up.data).hexdigest()
        if digest in existing:
            rejected.append(ImageRejection(
                filename=up.filename, status=409, reason="duplicate",
                detail=f"the map already has this image (sha256 {digest[:12]}...)"))
            continue
        existing.add(digest)
        source = "form" if position is not None else "exif"
        candidates.append((up, header, pos, digest, source))
    return rejected, candidates


def _check_one(up: Upload, position: GivenPosition | None,
               settings: Settings) -> tuple[ImageHeader, GivenPosition]:
    from vloc.workers.core.exif import read_gps

    if len(up.data) > settings.max_upload_bytes:
        raise Problem(413, f"{len(up.data)} bytes exceed the limit of "
                      f"{settings.max_upload_bytes} bytes per image", kind=ProblemKind.TOO_LARGE)
    header = check_image(up.data, max_pixels=settings.max_pixels)
    if position is not None:
        return header, position
    try:
        tag = read_gps(up.data)
    except ValueError as exc:
        raise Problem(422, f"malformed EXIF GPS: {exc}", kind=ProblemKind.BAD_GPS) from None
    if tag is None:
        raise Problem(422, "the image has no GPS position in its EXIF; give lat and lon "
                      "form fields with a single file", kind=ProblemKind.NO_GPS)
    if tag.alt is not None and not MIN_ALT_M <= tag.alt <= MAX_ALT_M:
        raise Problem(422, f"EXIF GPS altitude {tag.alt:g} m is outside [{MIN_ALT_M:g}, "
                      f"{MAX_ALT_M:g}] m", kind=ProblemKind.BAD_GPS)
    # Camera-local time without an offset: kept as is, labelled UTC. Only differences
    # between capture times are used (the platform's speed), which this keeps. A time
    # outside 1990..tomorrow is a clock that was never set: treated as absent, as a
    # damaged time stamp is.
    captured = aware(tag.captured_at)
    if captured is not None and not plausible_time(captured):
        captured = None
    return header, GivenPosition(tag.lat, tag.lon, tag.alt, captured)


def _store(db_sessions: sessionmaker[Session], map_id: uuid.UUID, good: list,
           settings: Settings, flight: str | None) -> list[MapImageRead]:
    folder = settings.images_dir(str(map_id))
    folder.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    with db_sessions() as db:
        try:
            map_ = db.get(Map, map_id)
            if map_ is None:
                raise not_found("map", map_id)  # deleted while the workers decoded
            rows = []
            for up, header, pos, digest, source in good:
                path = folder / f"{digest}{header.suffix}"
                if not path.exists():
                    tmp = path.with_suffix(path.suffix + ".part")
                    tmp.write_bytes(up.data)
                    os.replace(tmp, path)
                    written.append(path)
                row = MapImage(map_id=map_id, filename=_clean_name(up.filename),
                               file_hash=digest, content_type=header.content_type,
                               byte_size=len(up.data), width=header.width,
                               height=header.height, lat=pos.lat, lon=pos.lon, alt=pos.alt,
                               captured_at=pos.captured_at, flight=flight,
                               position_source=source)
                db.add(row)
                rows.append(row)
            if map_.status != MapStatus.BUILDING:
                map_.status = MapStatus.UNBUILT
            db.commit()
            return [MapImageRead.model_validate(r) for r in rows]
        except BaseException:
            db.rollback()
            for path in written:
                path.unlink(missing_ok=True)
            raise


def _clean_name(filename: str | None) -> str:
    name = Path(filename or "image").name
    return name[:255] or "image"


def image_path(settings: Settings, image: MapImage) -> Path:
    suffix = ".png" if image.content_type == "image/png" else ".jpg"
    return settings.images_dir(str(image.map_id)) / f"{image.file_hash}{suffix}"
