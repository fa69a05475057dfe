"""Sessions: create (validated against the core's localisers), read with statistics, delete."""

from __future__ import annotations

import asyncio
import math
import secrets
import threading
from dataclasses import dataclass
from datetime import timedelta
from functools import lru_cache

from sqlalchemy import delete, func, select, text
from sqlalchemy.orm import Session, sessionmaker

from vloc.app.db import new_id, utcnow
from vloc.app.engine import WorkerDied
from vloc.app.maps.models import Map
from vloc.app.problems import Problem, ProblemKind, not_found
from vloc.app.security import hash_secret, new_token
from vloc.app.sessions import pose, store
from vloc.app.sessions.admission import revision_missing
from vloc.app.sessions.models import Frame, FrameStatus, LocalisationSession, Pose
from vloc.app.sessions.params import SessionCreate
from vloc.app.sessions.registry import SessionRegistry
from vloc.app.sessions.schemas import (
    FrameError,
    InitialPose,
    NavigationRead,
    PoseEstimate,
    SessionRead,
    SessionStats,
)
from vloc.app.teach.service import navigation_path
from vloc.workers.core.geo import GeoOrigin

LATENCY_WINDOW = 1000
"""Latency percentiles are over the session's most recent estimates."""
INITIAL_POSE_MARGIN_M = 100.0
"""How far outside the map images' bounding box an initial pose may lie."""


@dataclass(frozen=True, slots=True)
class MapFrame:
    """The local frame and extent of one packed map revision."""

    origin: GeoOrigin
    extent: tuple[float, float, float, float]
    """(min_east, min_north, max_east, max_north), metres."""


@lru_cache(maxsize=64)
def map_frame(folder: str, map_id: str, revision: int) -> MapFrame:
    """Read a packed revision's frame (revisions never change once packed).

    Raises Problem 503 ``map-revision-missing``, without the data directory's path, when
    the revision's files are gone.
    """
    from vloc.workers.core.mapdata import MapData

    try:
        data = MapData.load(folder)
    except FileNotFoundError:
        raise revision_missing(map_id, revision) from None
    return MapFrame(data.origin, data.extent)


def check_initial_pose(frame: MapFrame, pose: InitialPose) -> None:
    """422 ``bad-initial-pose`` for a position outside the extent plus the margin."""
    if pose.lat is not None:
        east, north = (float(v) for v in frame.origin.to_local(pose.lat, pose.lon))
    else:
        east, north = pose.x, pose.y
    e0, n0, e1, n1 = frame.extent
    m = INITIAL_POSE_MARGIN_M
    if not (e0 - m <= east <= e1 + m and n0 - m <= north <= n1 + m):
        raise Problem(422, f"the initial pose ({east:.1f} m east, {north:.1f} m north) lies "
                      f"outside the map's extent ({e0:.1f}..{e1:.1f} m east, "
                      f"{n0:.1f}..{n1:.1f} m north) plus {m:g} m", kind=ProblemKind.BAD_INITIAL_POSE)


def resolve_seed(body: SessionCreate) -> int:
    given = body.params.seed
    if given is not None and body.seed is not None and given != body.seed:
        raise Problem(422, f"seed {body.seed} and params.seed {given} disagree",
                      kind=ProblemKind.BAD_PARAMS)
    seed = body.seed if body.seed is not None else given
    return secrets.randbits(63) if seed is None else int(seed)


async def create_session(*, db_sessions: sessionmaker[Session], body: SessionCreate,
                         sessions: SessionRegistry) -> tuple[SessionRead, str]:
    """Validate, create the localiser in the engine, store; the session and its token.

    The engine may take a while (the worker loads the map, it may be busy with frames);
    nothing holds a database connection or a request thread while it does.
    """
    row, token = await asyncio.to_thread(_plan, db_sessions, body, sessions.settings)
    # The row takes its place under the cap before the engine opens it: concurrent creates
    # cannot all pass the count while each waits for the engine.
    await asyncio.to_thread(_reserve, db_sessions, row, sessions.settings.max_sessions)
    try:
        await sessions.open_new(row)
    except BaseException as exc:
        await asyncio.to_thread(_unreserve, db_sessions, row.id)
        if isinstance(exc, ValueError):
            raise Problem(422, f"the localiser refused the session: {exc}",
                          kind=ProblemKind.BAD_PARAMS) from None
        if isinstance(exc, WorkerDied | TimeoutError | RuntimeError):
            raise Problem(503, f"the engine could not open the session: {exc}",
                          kind=ProblemKind.ENGINE_UNAVAILABLE) from None
        raise
    try:
        read = await asyncio.to_thread(_read_new, db_sessions, row.id, sessions)
    except BaseException:
        sessions.forget(row.id)
        raise
    return read, token


def _plan(db_sessions: sessionmaker[Session], body: SessionCreate,
          settings) -> tuple[LocalisationSession, str]:
    from vloc.workers.core.localisers import validate_params

    with db_sessions() as db:
        map_ = db.get(Map, body.map_id)
        if map_ is None:
            raise not_found("map", body.map_id)
        if map_.revision == 0:
            raise Problem(409, "the map has not been built yet; POST /v1/maps/{id}/build",
                          kind=ProblemKind.MAP_NOT_BUILT)
        map_id, revision = map_.id, map_.revision
        navigation = _navigation(db, body, map_id)
        follows = _follows(body, navigation)
        if body.map_revision is not None:
            revision = _pinned_revision(db, map_id, body.map_revision)
    try:
        params = validate_params(body.mode, body.given_params())
    except ValueError as exc:
        raise Problem(422, str(exc), kind=ProblemKind.BAD_PARAMS) from None
    seed = resolve_seed(body)
    ttl_s = body.ttl_s if body.ttl_s is not None else settings.session_ttl_s
    if ttl_s > settings.max_session_ttl_s:
        raise Problem(422, f"ttl_s {ttl_s} is longer than this server allows "
                      f"({settings.max_session_ttl_s} s, VLOC_MAX_SESSION_TTL_S)",
                      kind=ProblemKind.BAD_PARAMS)
    params.pop("seed", None)  # the seed travels as its own argument
    token = new_token()
    row = LocalisationSession(id=new_id(), map_id=map_id, map_revision=revision,
                              mode=body.mode, params=params, seed=seed,
                              token_hash=hash_secret(token), frames_processed=0,
                              frames_failed=0, last_seq=None, status=store.ACTIVE,
                              ttl_s=ttl_s, last_active_at=utcnow(),
                              navigation=navigation, follows_map=follows)
    return row, token


def _follows(body: SessionCreate, navigation: dict | None) -> bool:
    """Whether the session follows its map: by default, unless it pins a revision or
    follows a route (its path was taught against the revision it starts on)."""
    fixed = ("map_revision" if body.map_revision is not None
             else "navigation" if navigation is not None else None)
    if fixed is None:
        return body.follow_map is not False
    if body.follow_map:
        raise Problem(422, f"follow_map cannot be true for a session given {fixed}: it stays "
                      "on the revision it starts on", kind=ProblemKind.BAD_PARAMS)
    return False


def _pinned_revision(db: Session, map_id, revision: int) -> int:
    """A revision a session may pin: recorded for the map and not dropped (404
    otherwise)."""
    from vloc.app.maps.models import MapRevision

    row = db.get(MapRevision, (map_id, revision))
    if row is None or row.dropped_at is not None:
        raise Problem(404, f"map {map_id} has no revision {revision}"
                      + (" any more: it was dropped" if row is not None else ""),
                      kind=ProblemKind.NOT_FOUND)
    return revision


def _navigation(db: Session, body: SessionCreate, map_id) -> dict | None:
    """The route part a session follows, copied into the session (a later rebuild or
    deletion of the route leaves the session's path as it was), and its parameters."""
    from vloc.workers.core.navigation.session import navigation_params

    nav = body.navigation
    if nav is None:
        return None
    given = nav.params.model_dump(exclude_unset=True)
    try:
        params = navigation_params(given)
    except ValueError as exc:
        raise Problem(422, f"navigation.params: {exc}", kind=ProblemKind.BAD_PARAMS) from None
    path = navigation_path(db, map_id=map_id, route_id=nav.route_id,
                           from_node=nav.from_node, to_node=nav.to_node)
    return {**path, "params": params}


_CAP_LOCK = threading.Lock()
"""Serialises the count and the insert of the session cap within one process."""
_CAP_LOCK_KEY = 0x766C6F6353455353
"""PostgreSQL advisory lock that serialises them across processes sharing the database."""


def _reserve(db_sessions: sessionmaker[Session], row: LocalisationSession,
             max_sessions: int) -> None:
    """Insert the session's row if fewer than ``max_sessions`` exist, as one step.

    Raises Problem 429 ``too-many-sessions`` (with ``Retry-After``) at the cap.
    """
    with _CAP_LOCK, db_sessions() as db:
        if db.get_bind().dialect.name == "postgresql":
            db.execute(text("SELECT pg_advisory_xact_lock(:key)"), {"key": _CAP_LOCK_KEY})
        existing = db.scalar(select(func.count(LocalisationSession.id)))
        if existing >= max_sessions:
            raise Problem(429, f"{existing} sessions exist, the most this server keeps "
                          f"(VLOC_MAX_SESSIONS); delete finished sessions first",
                          kind=ProblemKind.TOO_MANY_SESSIONS, headers={"Retry-After": "60"},
                          max_sessions=max_sessions)
        db.add(row)
        db.commit()


def _unreserve(db_sessions: sessionmaker[Session], session_id) -> None:
    """Give the place back: the engine could not open the session."""
    with db_sessions() as db:
        db.execute(delete(LocalisationSession).where(LocalisationSession.id == session_id))
        db.commit()


def _read_new(db_sessions: sessionmaker[Session], session_id,
              sessions: SessionRegistry) -> SessionRead:
    with db_sessions() as db:
        return read_session(db, row=db.get(LocalisationSession, session_id), sessions=sessions)


def list_sessions(db: Session, *, sessions: SessionRegistry, limit: int | None = None,
                  offset: int = 0) -> list[SessionRead]:
    rows = db.scalars(select(LocalisationSession)
                      .order_by(LocalisationSession.created_at, LocalisationSession.id)
                      .offset(offset).limit(limit))
    return [read_session(db, row=row, sessions=sessions) for row in list(rows)]


def read_session(db: Session, *, row: LocalisationSession,
                 sessions: SessionRegistry) -> SessionRead:
    # The frames still pending are counted before the session is read (again): when none
    # is, every frame accepted until now is stored, and the counters below include it. The
    # read transaction is ended first, since SQLite would otherwise keep its older snapshot.
    pending = sessions.pending(row.id)
    db.commit()
    db.refresh(row)
    total, sift, mean_ms = db.execute(
        select(func.count(Pose.id), func.count(Pose.id).filter(Pose.feature == "sift"),
               func.avg(Pose.processing_ms)).where(Pose.session_id == row.id)).one()
    latencies = sorted(db.scalars(
        select(Pose.latency_ms).where(Pose.session_id == row.id)
        .order_by(Pose.seq.desc()).limit(LATENCY_WINDOW)))
    last = db.scalar(select(Pose).where(Pose.session_id == row.id)
                     .order_by(Pose.seq.desc()).limit(1))
    stats = SessionStats(
        sift_share=sift / total if total else None,
        latency_ms_p50=_quantile(latencies, 0.5), latency_ms_p99=_quantile(latencies, 0.99),
        processing_ms_mean=float(mean_ms) if mean_ms is not None else None)
    return SessionRead(
        id=row.id, map_id=row.map_id, map_revision=row.map_revision,
        follows_map=row.follows_map, mode=row.mode,
        params=row.params, seed=row.seed, created_at=row.created_at, last_seq=row.last_seq,
        frames_processed=row.frames_processed, frames_failed=row.frames_failed,
        frames_pending=pending, stats=stats,
        last_pose=pose_read(last, row) if last is not None else None,
        navigation=_navigation_read(row.navigation), **lifetime(row))


def lifetime(row: LocalisationSession) -> dict:
    """The session's state and time to live, as :class:`SessionRead` fields."""
    last = row.last_active_at or row.created_at
    expires_at = last + timedelta(seconds=row.ttl_s)
    state = row.status if row.status == store.EXPIRED or expires_at >= utcnow() \
        else store.EXPIRED
    return {"state": state, "ttl_s": row.ttl_s, "last_active_at": last,
            "expires_at": expires_at}


def _navigation_read(nav: dict | None) -> NavigationRead | None:
    if nav is None:
        return None
    return NavigationRead(route_id=nav["route_id"], params=nav["params"],
                          nodes=[nav["nodes"][0], nav["nodes"][-1]], points=len(nav["points"]))


def list_poses(db: Session, *, row: LocalisationSession, after_seq: int | None,
               limit: int) -> list[PoseEstimate | FrameError]:
    """Estimates and frame errors after ``after_seq``, merged in sequence order."""
    poses = select(Pose).where(Pose.session_id == row.id)
    errors = select(Frame).where(Frame.session_id == row.id, Frame.status.in_(
        (FrameStatus.FAILED, FrameStatus.INTERRUPTED)))
    if after_seq is not None:
        poses, errors = poses.where(Pose.seq > after_seq), errors.where(Frame.seq > after_seq)
    found = [pose_read(p, row) for p in db.scalars(poses.order_by(Pose.seq).limit(limit))]
    found += [frame_error_read(f) for f in db.scalars(errors.order_by(Frame.seq).limit(limit))]
    return sorted(found, key=lambda m: m.seq)[:limit]


def delete_session(db: Session, *, row: LocalisationSession, sessions: SessionRegistry) -> None:
    session_id = row.id
    db.delete(row)
    db.commit()
    sessions.forget(session_id)


def pose_read(p: Pose, row: LocalisationSession) -> PoseEstimate:
    return pose.from_row(p, map_id=row.map_id, map_revision=row.map_revision)


def frame_error_read(f: Frame) -> FrameError:
    return FrameError(session_id=f.session_id, seq=f.seq, captured_at=f.captured_at,
                      kind=f.error_kind or "error", reason=f.error_reason or "",
                      latency_ms=f.latency_ms)


def _quantile(sorted_values: list[float], q: float) -> float | None:
    """Nearest-rank quantile of sorted values."""
    if not sorted_values:
        return None
    rank = min(len(sorted_values) - 1, max(0, math.ceil(q * len(sorted_values)) - 1))
    return float(sorted_values[rank])
