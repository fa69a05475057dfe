"""Session routes: create/list (admin); read, delete, frames, reset, initial pose (token)."""

from __future__ import annotations

import asyncio
import time
from datetime import UTC, datetime

from fastapi import APIRouter, Depends, Query, Request, Response
from fastapi.responses import JSONResponse

from app.deps import Ctx, DbSession, require_admin
from app.imagecheck import check_image, kind_of_content_type
from app.limits import too_large
from app.maps.service import check_position
from app.problems import Problem
from app.sessions import service
from app.sessions.dependencies import LiveSessionDep, SessionDep
from app.sessions.models import LocalisationSession
from app.sessions.schemas import (
    MAX_SEQ,
    FrameAccepted,
    FrameError,
    InitialPose,
    PoseEstimate,
    SessionCreate,
    SessionCreated,
    SessionRead,
)

router = APIRouter(prefix="/v1/sessions", tags=["sessions"])

FAILED_FRAME_STATUS = {"bad_image": 422, "worker_died": 503, "not_open": 503, "error": 500,
                       "not_stored": 500}


@router.post("", status_code=201, response_model=SessionCreated,
             dependencies=[Depends(require_admin)])
async def create_session(body: SessionCreate, ctx: Ctx, response: Response) -> SessionCreated:
    """Open a localisation session on a built map; the token is shown only here."""
    read, token = await service.create_session(db_sessions=ctx.db_sessions, body=body,
                                               runtime=ctx.runtime)
    response.headers["Location"] = f"/v1/sessions/{read.id}"
    return SessionCreated(**read.model_dump(), token=token)


@router.get("", response_model=list[SessionRead], dependencies=[Depends(require_admin)])
def list_sessions(db: DbSession, ctx: Ctx) -> list[SessionRead]:
    return service.list_sessions(db, runtime=ctx.runtime)


@router.get("/{session_id}", response_model=SessionRead)
def get_session(row: SessionDep, db: DbSession, ctx: Ctx) -> SessionRead:
    return service.read_session(db, row=row, runtime=ctx.runtime)


@router.delete("/{session_id}", status_code=204)
def delete_session(row: SessionDep, db: DbSession, ctx: Ctx) -> Response:
    service.delete_session(db, row=row, runtime=ctx.runtime)
    return Response(status_code=204)


@router.get("/{session_id}/poses", response_model=list[PoseEstimate | FrameError])
def list_poses(row: SessionDep, db: DbSession,
               after_seq: int | None = Query(None, ge=-1, le=MAX_SEQ),
               limit: int = Query(1000, ge=1, le=10000)) -> list[PoseEstimate | FrameError]:
    """The stored outcome of every answered frame in sequence order: its estimate, or the
    ``frame_error`` of a frame that gave none (interrupted ones included)."""
    return service.list_poses(db, row=row, after_seq=after_seq, limit=limit)


@router.post("/{session_id}/frames", status_code=202, response_model=FrameAccepted,
             responses={200: {"model": PoseEstimate, "description": "With ?wait=true"},
                        409: {"description": "Duplicate, stale or exhausted seq"},
                        413: {"description": "Body or image too large"},
                        415: {"description": "Not image/jpeg or image/png"},
                        422: {"description": "Empty, corrupt or truncated image; seq out of "
                                             "range"},
                        503: {"description": "Shutting down, or the frame could not be "
                                             "recorded"}},
             openapi_extra={"requestBody": {"required": True, "content": {
                 "image/jpeg": {"schema": {"type": "string", "format": "binary"}},
                 "image/png": {"schema": {"type": "string", "format": "binary"}}}}})
async def post_frame(request: Request, live: LiveSessionDep, ctx: Ctx,
                     seq: int | None = Query(None, ge=0, le=MAX_SEQ),
                     captured_at: datetime | None = Query(
                         None, description="ISO 8601 or seconds since the epoch"),
                     wait: bool = Query(False, description="Answer with the estimate")):
    """Queue one frame (the raw image is the body); its estimate goes to the stream."""
    t0 = time.perf_counter()
    declared = kind_of_content_type(request.headers.get("content-type"))
    if declared is None:
        raise Problem(415, "send the frame as the raw body with Content-Type image/jpeg or "
                      "image/png", kind="unsupported-media-type")
    data = await _read_body(request, ctx.settings.max_frame_bytes)
    try:
        check_image(data, max_pixels=ctx.settings.max_pixels, declared=declared)
    except Problem as p:
        ctx.metrics.frames_rejected.labels(p.kind or "bad-image").inc()
        raise
    captured = captured_at.replace(tzinfo=UTC) if captured_at is not None \
        and captured_at.tzinfo is None else captured_at
    runtime = ctx.runtime
    seq, queued = runtime.accept(live, data, seq=seq, captured_at=captured, t0=t0)
    fut = runtime.waiter(live, seq) if wait else None
    try:
        # Answered once the frame is recorded: an accepted frame survives a crash.
        await asyncio.shield(queued)
    except BaseException:  # refused, or the client went away
        runtime.drop_waiter(live, seq)
        raise
    if fut is None:
        return JSONResponse({"seq": seq}, status_code=202)
    try:
        msg = await asyncio.wait_for(fut, ctx.settings.frame_wait_timeout_s)
    except TimeoutError:
        runtime.drop_waiter(live, seq)
        raise Problem(504, f"no estimate for frame {seq} within "
                      f"{ctx.settings.frame_wait_timeout_s:g} s; it will still be streamed",
                      kind="estimate-timeout", seq=seq) from None
    if msg["type"] == "pose":
        return JSONResponse(msg, status_code=200)
    raise Problem(FAILED_FRAME_STATUS.get(msg["kind"], 500), msg["reason"],
                  kind=f"frame-{msg['kind'].replace('_', '-')}", seq=seq)


@router.post("/{session_id}/reset", response_model=SessionRead)
async def reset(live: LiveSessionDep, ctx: Ctx) -> SessionRead:
    """Global re-initialisation of the filter, after the frames already queued."""
    await _control(ctx, live.id, "reset")
    return await asyncio.to_thread(_read, ctx, live.id)


@router.post("/{session_id}/initial-pose", response_model=SessionRead)
async def set_initial_pose(body: InitialPose, live: LiveSessionDep, ctx: Ctx) -> SessionRead:
    """Start the filter around a known position (as AMCL's initial pose)."""
    if body.lat is not None:
        check_position(body.lat, body.lon, None)
        args = {"lat": body.lat, "lon": body.lon}
    else:
        args = {"x": body.x, "y": body.y}
    await _control(ctx, live.id, "set_initial_pose", sigma=body.sigma, **args)
    return await asyncio.to_thread(_read, ctx, live.id)


async def _control(ctx, session_id: str, op: str, **kwargs) -> None:
    await ctx.runtime.queued_before()  # in order after the frames already accepted
    try:
        await asyncio.wrap_future(ctx.engine.control(session_id, op, **kwargs))
    except ValueError as exc:
        raise Problem(422, str(exc), kind="bad-control") from None
    except (KeyError, RuntimeError) as exc:
        raise Problem(503, f"the engine could not {op.replace('_', ' ')}: {exc}",
                      kind="engine-unavailable") from None


def _read(ctx, session_id: str) -> SessionRead:
    import uuid

    with ctx.db_sessions() as db:
        row = db.get(LocalisationSession, uuid.UUID(session_id))
        if row is None:
            raise Problem(404, f"session {session_id} was deleted", kind="not-found")
        return service.read_session(db, row=row, runtime=ctx.runtime)


async def _read_body(request: Request, limit: int) -> bytes:
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > limit:
        raise too_large(limit)
    chunks, size = [], 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > limit:
            raise too_large(limit)
        chunks.append(chunk)
    return b"".join(chunks)
