"""Session routes: create/list (admin); read, delete, frames, reset, initial pose (token)."""

from __future__ import annotations

import asyncio
import time
from datetime import datetime

from fastapi import APIRouter, Depends, Query, Request, Response
from fastapi.responses import JSONResponse

from vloc.app.deps import Ctx, DbSession, require_admin
from vloc.app.imagecheck import check_image, kind_of_content_type
from vloc.app.limits import read_body
from vloc.app.problems import Problem, ProblemKind
from vloc.app.sessions import service
from vloc.app.sessions.dependencies import FrameMetadataDep, LiveSessionDep, SessionDep
from vloc.app.sessions.models import LocalisationSession
from vloc.app.sessions.params import SessionCreate
from vloc.app.sessions.schemas import (
    MAX_SEQ,
    FrameAccepted,
    FrameError,
    InitialPose,
    PoseEstimate,
    SessionCreated,
    SessionRead,
)
from vloc.app.validation import check_captured_at, check_position

router = APIRouter(prefix="/v1/sessions", tags=["sessions"])

FAILED_FRAME_STATUS = {"bad_image": 422, "worker_died": 503, "not_open": 503, "error": 500,
                       "not_stored": 500}


@router.post("", status_code=201, response_model=SessionCreated,
             dependencies=[Depends(require_admin)])
async def create_session(body: SessionCreate, ctx: Ctx, response: Response) -> SessionCreated:
    """Open a localisation session on a built map; the token is shown only here."""
    read, token = await service.create_session(db_sessions=ctx.db_sessions, body=body,
                                               sessions=ctx.sessions)
    response.headers["Location"] = f"/v1/sessions/{read.id}"
    return SessionCreated(**read.model_dump(), token=token)


@router.get("", response_model=list[SessionRead], dependencies=[Depends(require_admin)])
def list_sessions(db: DbSession, ctx: Ctx, limit: int = Query(100, ge=1, le=1000),
                  offset: int = Query(0, ge=0, le=2**31)) -> list[SessionRead]:
    """Sessions, oldest first: ``limit`` of them from ``offset``."""
    return service.list_sessions(db, sessions=ctx.sessions, limit=limit, offset=offset)


@router.get("/{session_id}", response_model=SessionRead)
def get_session(row: SessionDep, db: DbSession, ctx: Ctx) -> SessionRead:
    """A session: mode, parameters, state and time to live, counters, latency statistics
    and the last pose."""
    return service.read_session(db, row=row, sessions=ctx.sessions)


@router.delete("/{session_id}", status_code=204)
def delete_session(row: SessionDep, db: DbSession, ctx: Ctx) -> Response:
    """Close and delete a session with its poses; its streams are closed."""
    service.delete_session(db, row=row, sessions=ctx.sessions)
    return Response(status_code=204)


@router.get("/{session_id}/poses", response_model=list[PoseEstimate | FrameError])
def list_poses(row: SessionDep, db: DbSession,
               after_seq: int | None = Query(None, ge=-1, le=MAX_SEQ),
               limit: int = Query(1000, ge=1, le=10000)) -> list[PoseEstimate | FrameError]:
    """The stored outcome of every answered frame in sequence order: its estimate, or the
    ``frame_error`` of a frame that gave none (interrupted ones included)."""
    return service.list_poses(db, row=row, after_seq=after_seq, limit=limit)


@router.get("/{session_id}/frames/last", response_class=Response,
            responses={200: {"content": {"image/jpeg": {}, "image/png": {}},
                             "description": "The latest accepted frame; its seq in "
                                            "the X-Frame-Seq header"},
                       204: {"description": "No frame has arrived since the session was "
                                            "opened on this server"}})
def last_frame(live: LiveSessionDep) -> Response:
    """The latest frame this server accepted for the session, as it was sent. Frames are
    kept in memory only, up to 1 MiB: before the first one, after a larger one, and after a
    restart, the answer is 204."""
    if live.last_frame is None:
        return Response(status_code=204, headers={"Cache-Control": "no-store"})
    seq, data = live.last_frame
    media = "image/png" if data.startswith(b"\x89PNG") else "image/jpeg"
    return Response(data, media_type=media,
                    headers={"X-Frame-Seq": str(seq), "Cache-Control": "no-store"})


@router.post("/{session_id}/frames", status_code=202, response_model=FrameAccepted,
             responses={200: {"model": PoseEstimate, "description": "With ?wait=true"},
                        409: {"description": "Duplicate, stale or exhausted seq"},
                        413: {"description": "Body or image too large"},
                        415: {"description": "Not image/jpeg or image/png"},
                        422: {"description": "Empty, corrupt or truncated image; seq, "
                                             "captured_at or metadata out of range "
                                             "(bad-metadata names the field)"},
                        429: {"description": "Too many frames of the session queued, or "
                                             "more than its share of the server's "
                                             "(Retry-After)"},
                        500: {"description": "With ?wait=true: the frame was accepted and "
                                             "gave no estimate (frame-error), or its outcome "
                                             "could not be stored (frame-not-stored)"},
                        503: {"description": "Shutting down, the server holds as many "
                                             "frames as it takes (Retry-After), or the "
                                             "frame could not be recorded"}},
             openapi_extra={"requestBody": {"required": True, "content": {
                 "image/jpeg": {"schema": {"type": "string", "format": "binary"}},
                 "image/png": {"schema": {"type": "string", "format": "binary"}}}}})
async def post_frame(request: Request, live: LiveSessionDep, ctx: Ctx,
                     metadata: FrameMetadataDep,
                     seq: int | None = Query(None, ge=0, le=MAX_SEQ),
                     captured_at: datetime | None = Query(
                         None, description="ISO 8601 or seconds since the epoch; from 1990 "
                                           "to one day from now"),
                     wait: bool = Query(False, description="Answer with the estimate")):
    """Queue one frame (the raw image is the body); its estimate goes to the stream.

    The device's other sensors may come with it as query parameters (each optional, all
    validated before the frame is accepted): ``heading_deg``, ``heading_accuracy_deg``,
    ``altitude_m``, ``gps_lat`` + ``gps_lon`` (+ ``gps_accuracy_m``), ``velocity_east`` +
    ``velocity_north``.
    """
    t0 = time.perf_counter()
    declared = kind_of_content_type(request.headers.get("content-type"))
    if declared is None:
        raise Problem(415, "send the frame as the raw body with Content-Type image/jpeg or "
                      "image/png", kind=ProblemKind.UNSUPPORTED_MEDIA_TYPE)
    intake = ctx.intake
    limit = ctx.settings.max_frame_bytes
    try:
        captured = check_captured_at(captured_at)
        # the body's room is taken before it is read: bodies in flight are what fills memory
        with intake.budget.reading(live.id, _declared_size(request, limit)):
            data = await read_body(request, limit)
            header = check_image(data, max_pixels=ctx.settings.max_pixels, declared=declared)
            seq, queued = await intake.accept(live, data, seq=seq, captured_at=captured,
                                              t0=t0, metadata=metadata, header=header,
                                              admitted=True)
    except Problem as p:
        ctx.metrics.frames_rejected.labels(p.kind or ProblemKind.BAD_IMAGE).inc()
        raise
    fut = intake.waiter(live, seq) if wait else None
    try:
        # Answered once the frame is recorded: an accepted frame survives a crash.
        await asyncio.shield(queued)
    except BaseException:  # refused, or the client went away
        intake.drop_waiter(live, seq)
        raise
    if fut is None:
        return JSONResponse({"seq": seq}, status_code=202)
    try:
        msg = await asyncio.wait_for(fut, ctx.settings.frame_wait_timeout_s)
    except TimeoutError:
        intake.drop_waiter(live, seq)
        raise Problem(504, f"no estimate for frame {seq} within "
                      f"{ctx.settings.frame_wait_timeout_s:g} s; it will still be streamed",
                      kind=ProblemKind.ESTIMATE_TIMEOUT, seq=seq) from None
    if msg["type"] == "pose":  # the message as the stream has it, written once
        return Response(msg.text, status_code=200, media_type="application/json")
    raise Problem(FAILED_FRAME_STATUS.get(msg["kind"], 500), msg["reason"],
                  kind=ProblemKind(f"frame-{msg['kind'].replace('_', '-')}"), seq=seq)


def _declared_size(request: Request, limit: int) -> int:
    """The body's size as declared, else (chunked) the most it may be."""
    declared = request.headers.get("content-length")
    return min(int(declared), limit) if declared is not None and declared.isdigit() else limit


@router.post("/{session_id}/reset", response_model=SessionRead)
async def reset(live: LiveSessionDep, ctx: Ctx) -> SessionRead:
    """Global re-initialisation of the filter, after the frames already queued."""
    await _control(ctx, live, "reset")
    ctx.sessions.restart_convergence(live)
    return await asyncio.to_thread(_read, ctx, live.id)


@router.post("/{session_id}/initial-pose", response_model=SessionRead)
async def set_initial_pose(body: InitialPose, live: LiveSessionDep, ctx: Ctx) -> SessionRead:
    """Start the filter around a known position (as AMCL's initial pose)."""
    spec = live.spec
    frame = await asyncio.to_thread(service.map_frame, spec.map_folder, spec.map_id,
                                    spec.revision)
    service.check_initial_pose(frame, body)
    if body.lat is not None:
        check_position(body.lat, body.lon, None)
        args = {"lat": body.lat, "lon": body.lon}
    else:
        args = {"x": body.x, "y": body.y}
    if body.heading_deg is not None:
        args["heading_deg"] = body.heading_deg
        if body.heading_sigma_deg is not None:
            args["heading_sigma_deg"] = body.heading_sigma_deg
    await _control(ctx, live, "set_initial_pose", sigma=body.sigma, **args)
    ctx.sessions.restart_convergence(live)
    return await asyncio.to_thread(_read, ctx, live.id)


@router.post("/{session_id}/keepalive", response_model=SessionRead,
             responses={410: {"description": "The session has expired (session-expired)"}})
async def keep_alive(live: LiveSessionDep, ctx: Ctx) -> SessionRead:
    """Restart the session's time to live without sending a frame."""
    await ctx.sessions.keep_alive_stored(live)
    return await asyncio.to_thread(_read, ctx, live.id)


async def _control(ctx, live, op: str, **kwargs) -> None:
    try:
        # in order after the frames already accepted
        await ctx.intake.control(live, op, **kwargs)
    except ValueError as exc:
        raise Problem(422, str(exc), kind=ProblemKind.BAD_CONTROL) from None
    except (KeyError, RuntimeError) as exc:
        raise Problem(503, f"the engine could not {op.replace('_', ' ')}: {exc}",
                      kind=ProblemKind.ENGINE_UNAVAILABLE) from None


def _read(ctx, session_id: str) -> SessionRead:
    import uuid

    with ctx.db_sessions() as db:
        row = db.get(LocalisationSession, uuid.UUID(session_id))
        if row is None:
            raise Problem(404, f"session {session_id} was deleted", kind=ProblemKind.NOT_FOUND)
        return service.read_session(db, row=row, sessions=ctx.sessions)
