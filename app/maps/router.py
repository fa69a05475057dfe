"""Map routes (admin): create, list, read, delete, add images, build, manage revisions."""

from __future__ import annotations

from datetime import datetime

from fastapi import APIRouter, Depends, File, Form, Query, Response, UploadFile
from fastapi import Path as PathParam
from fastapi.responses import FileResponse

from vloc.app.deps import Ctx, DbSession, SettingsDep, require_admin
from vloc.app.jobs.service import forget_reconstruction, start_build
from vloc.app.maps import history, service
from vloc.app.maps.coverage import Coverage, covering_maps
from vloc.app.maps.dependencies import ImageVerifier, MapDep, parse_id
from vloc.app.maps.models import MapImage
from vloc.app.maps.schemas import (
    BuildAccepted,
    ImageUploadResult,
    MapCreate,
    MapImageRead,
    MapRead,
    RevisionRead,
)
from vloc.app.problems import Problem, ProblemKind
from vloc.app.validation import MAX_ALT_M, MIN_ALT_M, aware, check_text

router = APIRouter(prefix="/v1/maps", tags=["maps"], dependencies=[Depends(require_admin)])


@router.post("", status_code=201, response_model=MapRead)
def create_map(body: MapCreate, db: DbSession, response: Response) -> MapRead:
    """Create an empty map; add images, then build it."""
    m = service.create_map(db, name=body.name)
    response.headers["Location"] = f"/v1/maps/{m.id}"
    return service.read_map(db, map_=m)


@router.get("", response_model=list[MapRead])
def list_maps(db: DbSession, limit: int = Query(100, ge=1, le=1000),
              offset: int = Query(0, ge=0, le=2**31)) -> list[MapRead]:
    """Maps, oldest first: ``limit`` of them from ``offset``."""
    return service.list_maps(db, limit=limit, offset=offset)


@router.get("/coverage", response_model=list[Coverage])
def coverage(db: DbSession,
             lat: float = Query(ge=-90, le=90, allow_inf_nan=False, description="WGS84"),
             lon: float = Query(ge=-180, le=180, allow_inf_nan=False),
             radius_m: float = Query(50.0, gt=0, le=100_000, allow_inf_nan=False,
                                     description="How near a map image must be")
             ) -> list[Coverage]:
    """Is this position covered? The built maps with an image within ``radius_m`` of it,
    nearest first; an empty list when none."""
    return covering_maps(db, lat=lat, lon=lon, radius_m=radius_m)


@router.get("/{map_id}", response_model=MapRead)
def get_map(map_: MapDep, db: DbSession) -> MapRead:
    """A map: build status, revision, image counts, extent and local frame."""
    return service.read_map(db, map_=map_)


@router.delete("/{map_id}", status_code=204)
def delete_map(map_: MapDep, db: DbSession, settings: SettingsDep) -> Response:
    """Delete a map with its images and packed revisions (409 while sessions use it or
    a build runs)."""
    service.delete_map(db, map_=map_, settings=settings)
    return Response(status_code=204)


@router.get("/{map_id}/images", response_model=list[MapImageRead])
def list_images(map_: MapDep, db: DbSession, limit: int = Query(1000, ge=1, le=10000),
                after_id: int = Query(0, ge=0, lt=2**63,
                                      description="Images with an id above this one")
                ) -> list[MapImage]:
    """The map's images in id order: ``limit`` of them after ``after_id`` (give the last
    id of a page to read the next)."""
    return service.list_images(db, map_=map_, limit=limit, after_id=after_id)


@router.get("/{map_id}/images/{image_id}/file", response_class=FileResponse,
            responses={200: {"content": {"image/jpeg": {}, "image/png": {}},
                             "description": "The image as uploaded"}})
def get_image_file(map_: MapDep, db: DbSession, settings: SettingsDep,
                   image_id: int = PathParam(ge=1, lt=2**63)) -> FileResponse:
    """The image file as it was uploaded (the viewer's thumbnails)."""
    image = service.get_image(db, map_=map_, image_id=image_id)
    path = service.image_path(settings, image)
    if not path.is_file():
        raise Problem(404, f"the file of image {image_id} is missing", kind=ProblemKind.NOT_FOUND)
    # content-addressed: the file of an image id never changes
    return FileResponse(path, media_type=image.content_type,
                        headers={"Cache-Control": "private, max-age=86400"})


@router.delete("/{map_id}/images/{image_id}", status_code=204)
def delete_image(map_: MapDep, db: DbSession, settings: SettingsDep,
                 image_id: int = PathParam(ge=1, lt=2**63)) -> Response:
    """Delete one image (its features and file); the next build leaves it out."""
    service.delete_image(db, map_=map_, image_id=image_id, settings=settings)
    return Response(status_code=204)


@router.post("/{map_id}/images", status_code=201, response_model=ImageUploadResult,
             responses={413: {"description": "Too large"}, 415: {"description": "Not an image"},
                        422: {"description": "No file accepted"}})
async def add_images(map_id: str, settings: SettingsDep, ctx: Ctx, verify: ImageVerifier,
                     files: list[UploadFile] = File(min_length=1,
                                                    description="JPEG/PNG map images"),
                     lat: float | None = Form(None, ge=-90, le=90, allow_inf_nan=False,
                                              description="Only with a single file"),
                     lon: float | None = Form(None, ge=-180, le=180, allow_inf_nan=False,
                                              description="Only with a single file"),
                     alt: float | None = Form(None, ge=MIN_ALT_M, le=MAX_ALT_M,
                                              allow_inf_nan=False, description="Metres"),
                     captured_at: datetime | None = Form(
                         None, description="ISO 8601; from 1990 to one day from now"),
                     flight: str | None = Form(
                         None, min_length=1, max_length=64,
                         description="The flight (or pass) these images belong to, for a "
                                     "map of several flights over the same ground: its "
                                     "self-check reports each flight's accuracy"),
                     ) -> ImageUploadResult:
    """Add geotagged images: GPS from EXIF, or ``lat``/``lon`` fields for one file;
    ``flight`` names the flight they belong to (by default, images are grouped into flights
    by their capture times: a pause of over 30 minutes starts another)."""
    if (lat is None) != (lon is None):
        raise Problem(422, "give both lat and lon, or neither", kind=ProblemKind.BAD_POSITION)
    position = None
    if lat is not None:
        position = service.GivenPosition(lat, lon, alt, aware(captured_at))
    # One byte past the limit is enough to know that a file is too large.
    uploads = [service.Upload(check_text(f.filename or "image", "filename"),
                              await f.read(settings.max_upload_bytes + 1))
               for f in files]
    return await service.add_images(db_sessions=ctx.db_sessions,
                                    map_id=parse_id(map_id, "map"), uploads=uploads,
                                    position=position, settings=settings, verify=verify,
                                    flight=None if flight is None
                                    else check_text(flight, "flight"))


@router.post("/{map_id}/build", status_code=202, response_model=BuildAccepted)
def build_map(map_: MapDep, db: DbSession, ctx: Ctx, response: Response,
              force: bool = Query(False, description="Pack a new revision even when the "
                                                     "current one holds every image"),
              full: bool = Query(False, description="Reconstruct the map's camera geometry "
                                                    "whole instead of registering the images "
                                                    "added since the last build into it, and "
                                                    "train its place vocabularies afresh "
                                                    "(implies force)")
              ) -> BuildAccepted:
    """Extract the new images' features and pack a new revision, in the background
    (409 ``map-up-to-date`` when there is nothing new, unless ``force`` or ``full``)."""
    job = start_build(db, map_=map_, force=force, full=full)
    if full:
        forget_reconstruction(ctx.settings.tie_store_dir(str(map_.id)))
    ctx.builds.launch(job.id)
    response.headers["Location"] = f"/v1/jobs/{job.id}"
    return BuildAccepted(job_id=job.id, status=job.status)


RevisionNumber = PathParam(ge=1, lt=2**31, description="A revision of the map")


@router.get("/{map_id}/revisions", response_model=list[RevisionRead])
def list_revisions(map_: MapDep, db: DbSession, settings: SettingsDep) -> list[RevisionRead]:
    """The map's packed revisions, newest first: what each holds, what changed since the
    revision it was built on, its self-check, its size on disk and who uses it."""
    return history.list_revisions(db, map_=map_, settings=settings)


@router.post("/{map_id}/revisions/{revision}/restore", response_model=MapRead,
             responses={409: {"description": "A build is running, or the revision cannot be "
                                             "restored"}})
def restore_revision(map_: MapDep, db: DbSession, ctx: Ctx,
                     revision: int = RevisionNumber) -> MapRead:
    """Make an earlier (or later) revision the current one again: new sessions use it,
    open sessions that follow the map move to it before their next frame (those that pin
    a revision keep theirs), images it does not hold wait for the next build."""
    history.restore_revision(db, map_=map_, revision=revision, settings=ctx.settings)
    ctx.intake.following.map_revised(str(map_.id), revision)
    return service.read_map(db, map_=map_)


@router.delete("/{map_id}/revisions/{revision}", status_code=204,
               responses={409: {"description": "The current revision, or one in use"}})
def drop_revision(map_: MapDep, db: DbSession, settings: SettingsDep,
                  revision: int = RevisionNumber) -> Response:
    """Delete a revision that is neither current nor used by an active session, with its
    files."""
    history.drop_revision(db, map_=map_, revision=revision, settings=settings)
    return Response(status_code=204)
