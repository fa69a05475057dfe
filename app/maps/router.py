"""Map routes (admin): create, list, read, delete, add images, build."""

from __future__ import annotations

from datetime import datetime

from fastapi import APIRouter, Depends, File, Form, Path, Response, UploadFile

from app.deps import Ctx, DbSession, SettingsDep, require_admin
from app.jobs.service import start_build
from app.maps import service
from app.maps.dependencies import ImageVerifier, MapDep, parse_id
from app.maps.models import MapImage
from app.maps.schemas import BuildAccepted, ImageUploadResult, MapCreate, MapImageRead, MapRead
from app.problems import Problem
from app.validation import MAX_ALT_M, MIN_ALT_M, aware

router = APIRouter(prefix="/v1/maps", tags=["maps"], dependencies=[Depends(require_admin)])


@router.post("", status_code=201, response_model=MapRead)
def create_map(body: MapCreate, db: DbSession, response: Response) -> MapRead:
    m = service.create_map(db, name=body.name)
    response.headers["Location"] = f"/v1/maps/{m.id}"
    return service.read_map(db, map_=m)


@router.get("", response_model=list[MapRead])
def list_maps(db: DbSession) -> list[MapRead]:
    return service.list_maps(db)


@router.get("/{map_id}", response_model=MapRead)
def get_map(map_: MapDep, db: DbSession) -> MapRead:
    return service.read_map(db, map_=map_)


@router.delete("/{map_id}", status_code=204)
def delete_map(map_: MapDep, db: DbSession, settings: SettingsDep) -> Response:
    service.delete_map(db, map_=map_, settings=settings)
    return Response(status_code=204)


@router.get("/{map_id}/images", response_model=list[MapImageRead])
def list_images(map_: MapDep, db: DbSession) -> list[MapImage]:
    return service.list_images(db, map_=map_)


@router.delete("/{map_id}/images/{image_id}", status_code=204)
def delete_image(map_: MapDep, db: DbSession, settings: SettingsDep,
                 image_id: int = Path(ge=1, lt=2**63)) -> Response:
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
                     ) -> ImageUploadResult:
    """Add geotagged images: GPS from EXIF, or ``lat``/``lon`` fields for one file."""
    if (lat is None) != (lon is None):
        raise Problem(422, "give both lat and lon, or neither", kind="bad-position")
    position = None
    if lat is not None:
        position = service.GivenPosition(lat, lon, alt, aware(captured_at))
    # One byte past the limit is enough to know that a file is too large.
    uploads = [service.Upload(f.filename or "image", await f.read(settings.max_upload_bytes + 1))
               for f in files]
    return await service.add_images(db_sessions=ctx.db_sessions,
                                    map_id=parse_id(map_id, "map"), uploads=uploads,
                                    position=position, settings=settings, verify=verify)


@router.post("/{map_id}/build", status_code=202, response_model=BuildAccepted)
def build_map(map_: MapDep, db: DbSession, ctx: Ctx, response: Response) -> BuildAccepted:
    """Extract the new images' features and pack a new revision, in the background."""
    job = start_build(db, map_=map_)
    ctx.builds.launch(job.id)
    response.headers["Location"] = f"/v1/jobs/{job.id}"
    return BuildAccepted(job_id=job.id, status=job.status)
