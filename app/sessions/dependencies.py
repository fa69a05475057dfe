"""Fetch-or-404 and authorisation for sessions: the admin key or the session's own token."""

from __future__ import annotations

import uuid
from typing import Annotated

from fastapi import Depends, Query, Security
from starlette.requests import HTTPConnection

from vloc.app.context import AppContext
from vloc.app.deps import AdminSchemes, Ctx, DbSession, session_bearer, unauthenticated
from vloc.app.maps.dependencies import parse_id
from vloc.app.problems import Problem, ProblemKind, not_found
from vloc.app.security import matches, presented_secret
from vloc.app.sessions.live import LiveSession
from vloc.app.sessions.models import LocalisationSession
from vloc.app.sessions.registry import expired_problem
from vloc.app.validation import check_metadata
from vloc.workers.core.metadata import FrameMetadata


def authorise(secret: str | None, token_hash: str, ctx: AppContext, session_id: object) -> None:
    """401 without credentials; 403 unless they are the admin key or this session's token."""
    if secret is None:
        raise unauthenticated("a session token is required: Authorization: Bearer <token>")
    if not (matches(secret, token_hash) or matches(secret, ctx.admin_key_hash)):
        raise Problem(403, f"these credentials do not open session {session_id}",
                      kind=ProblemKind.FORBIDDEN)


SessionScheme = Security(session_bearer)


def get_session(session_id: str, conn: HTTPConnection, db: DbSession, ctx: Ctx,
                _token=SessionScheme, _bearer=AdminSchemes[0],
                _key=AdminSchemes[1]) -> LocalisationSession:
    secret = presented_secret(conn)
    if secret is None:
        raise unauthenticated("a session token is required: Authorization: Bearer <token>")
    row = db.get(LocalisationSession, parse_id(session_id, "session"))
    if row is None:
        raise not_found("session", session_id)
    authorise(secret, row.token_hash, ctx, session_id)
    return row


SessionDep = Annotated[LocalisationSession, Depends(get_session)]


async def get_live_session(session_id: str, conn: HTTPConnection, ctx: Ctx,
                           _token=SessionScheme, _bearer=AdminSchemes[0],
                           _key=AdminSchemes[1]) -> LiveSession:
    """The live session (no database round trip once loaded), authorised; 410
    ``session-expired`` past its time to live."""
    secret = presented_secret(conn)
    if secret is None:
        raise unauthenticated("a session token is required: Authorization: Bearer <token>")
    live = await ctx.sessions.get(parse_id(session_id, "session"))
    if live is None:
        raise not_found("session", session_id)
    authorise(secret, live.token_hash, ctx, session_id)
    if live.expired() and not live.arrivals:
        await ctx.sessions.expire(live)
        raise expired_problem(session_id)
    return live


LiveSessionDep = Annotated[LiveSession, Depends(get_live_session)]


def session_uuid(live: LiveSession) -> uuid.UUID:
    return uuid.UUID(live.id)


def frame_metadata(
    heading_deg: float | None = Query(
        None, description="Compass bearing of the frame's top edge, degrees clockwise from "
                          "north, [0, 360)"),
    heading_accuracy_deg: float | None = Query(
        None, description="Its standard deviation, degrees, (0, 180]; needs heading_deg"),
    altitude_m: float | None = Query(None, description="Altitude, metres, [-500, 10000]"),
    gps_lat: float | None = Query(None, description="GNSS latitude, WGS84 degrees; with "
                                                    "gps_lon"),
    gps_lon: float | None = Query(None, description="GNSS longitude; with gps_lat"),
    gps_accuracy_m: float | None = Query(
        None, description="The fix's horizontal accuracy (one standard deviation), metres, "
                          "> 0; needs the fix"),
    velocity_east: float | None = Query(
        None, description="Ground velocity east, m/s; with velocity_north (at most 150 m/s)"),
    velocity_north: float | None = Query(None, description="Ground velocity north, m/s"),
) -> FrameMetadata | None:
    """The frame's optional sensor reports, validated (422 ``bad-metadata`` naming the
    field); None when the request carries none."""
    return check_metadata(dict(
        heading_deg=heading_deg, heading_accuracy_deg=heading_accuracy_deg,
        altitude_m=altitude_m, gps_lat=gps_lat, gps_lon=gps_lon,
        gps_accuracy_m=gps_accuracy_m, velocity_east=velocity_east,
        velocity_north=velocity_north))


FrameMetadataDep = Annotated[FrameMetadata | None, Depends(frame_metadata)]
