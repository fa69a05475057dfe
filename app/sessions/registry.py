"""The sessions one API process holds: opened, reloaded from their checkpoints, kept alive,
expired and forgotten.

A session lives in the database; an API process holds it (a :class:`LiveSession`, and its
localiser in the engine) from its creation or its first request here until it expires, is
deleted, or the process stops. What arrives for it (frames, controls) goes through
:mod:`app.sessions.intake`; a session that follows its map moves to the map's new revisions
through :mod:`app.sessions.following`.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import uuid
from collections.abc import Callable

from sqlalchemy.orm import Session, sessionmaker

from vloc.app.config import Settings
from vloc.app.db import utcnow
from vloc.app.engine import Engine, SessionSpec
from vloc.app.metrics import Metrics
from vloc.app.problems import Problem, ProblemKind
from vloc.app.sessions import store
from vloc.app.sessions.admission import check_revision, spec_for
from vloc.app.sessions.live import LiveSession
from vloc.app.sessions.models import LocalisationSession
from vloc.app.sessions.schemas import FrameError
from vloc.app.stream.hub import CLOSED, EXPIRED, LocalHub

log = logging.getLogger(__name__)

OPEN_TIMEOUT_S = 120.0


class SessionRegistry:
    """The live sessions of this API process, by id.

    ``on_forget`` is called with a session's id when the process lets it go (deleted,
    expired): whoever keeps something per session drops it there.
    """

    def __init__(self, *, settings: Settings, db_sessions: sessionmaker[Session],
                 engine: Engine, hub: LocalHub, metrics: Metrics) -> None:
        self.settings = settings
        self.db_sessions = db_sessions
        self.engine = engine
        self.hub = hub
        self.metrics = metrics
        self.owner = settings.instance_name
        self.loop: asyncio.AbstractEventLoop | None = None
        self.on_forget: Callable[[str], None] = lambda session_id: None
        self._live: dict[str, LiveSession] = {}
        self._opening: dict[str, asyncio.Future] = {}
        self._seq_floor: dict[str, int] = {}
        """Last seq of a live session dropped for a reload, until the reload reads it."""
        self._lock = threading.Lock()

    def find(self, session_id: str) -> LiveSession | None:
        """The session if this process holds it now (any thread; never loads it)."""
        return self._live.get(session_id)

    def held(self) -> list[LiveSession]:
        """Every session this process holds now (any thread)."""
        return list(self._live.values())

    def __len__(self) -> int:
        return len(self._live)

    def __contains__(self, session_id: str) -> bool:
        return session_id in self._live

    # -- opening ----------------------------------------------------------------------------

    async def open_new(self, row: LocalisationSession) -> LiveSession:
        """Create a new session's localiser in the engine."""
        spec = spec_for(row, self.settings)
        check_revision(spec)
        try:
            await asyncio.wait_for(asyncio.wrap_future(self.engine.open_session(spec)),
                                   OPEN_TIMEOUT_S)
        except BaseException:
            self.engine.close_session(spec.session_id)
            raise
        return self._hold(LiveSession(str(row.id), row.token_hash, spec, row.last_seq,
                                      ttl_s=row.ttl_s, last_active=row.last_active_at or utcnow(),
                                      follows_map=row.follows_map))

    async def get(self, session_id: uuid.UUID) -> LiveSession | None:
        """The live session, loaded from its checkpoint when this process does not hold it.

        None when the session does not exist; a 410 :class:`Problem` when it has expired.
        """
        key = str(session_id)
        live = self._live.get(key)
        if live is not None:
            return live
        if key in self._opening:
            return await asyncio.shield(self._opening[key])
        fut = self.loop.create_future()
        self._opening[key] = fut
        try:
            live = await self._load(session_id)
            fut.set_result(live)
            return live
        except BaseException as exc:
            fut.set_exception(exc)
            fut.exception()  # marks it retrieved when nobody else waited on it
            raise
        finally:
            del self._opening[key]

    async def _load(self, session_id: uuid.UUID) -> LiveSession | None:
        row, recorded, converged = await asyncio.to_thread(self._read_row, session_id)
        if row is None:
            return None
        if row.status == store.EXPIRED:
            raise expired_problem(session_id)
        spec = spec_for(row, self.settings)
        # Never reuse a seq: the highest ever accepted, answered or not, counts.
        known = [s for s in (row.last_seq, recorded, self._seq_floor.pop(spec.session_id, None))
                 if s is not None]
        last_seq = max(known, default=None)
        await self._restore(spec, row.state, last_seq)
        return self._hold(LiveSession(spec.session_id, row.token_hash, spec, last_seq,
                                      converged=converged, ttl_s=row.ttl_s,
                                      last_active=row.last_active_at or row.created_at,
                                      follows_map=row.follows_map))

    def _hold(self, live: LiveSession) -> LiveSession:
        with self._lock:
            self._live[live.id] = live
        self.metrics.live_sessions.set(len(self._live))
        return live

    async def _restore(self, spec: SessionSpec, state: bytes | None,
                       last_seq: int | None) -> None:
        """Open a stored session in the engine from its checkpoint (on a shared engine, one
        that another API process opened stays as it is)."""
        check_revision(spec)
        try:
            await asyncio.wrap_future(self.engine.open_session(spec, state=state,
                                                               last_seq=last_seq))
        except Exception as exc:
            # The worker's message may name files under the data directory: logged only.
            log.warning("session %s could not be restored", spec.session_id, exc_info=exc)
            raise Problem(503, f"the session could not be restored ({type(exc).__name__}); "
                          "see the server log", kind=ProblemKind.SESSION_UNAVAILABLE) from None

    async def reopen(self, live: LiveSession) -> None:
        """The engine lost the session (its actor died and came back empty): open it again
        from the checkpoint in the database."""
        row, recorded, _ = await asyncio.to_thread(self._read_row, uuid.UUID(live.id))
        if row is None:
            raise Problem(404, f"session {live.id} was deleted", kind=ProblemKind.NOT_FOUND)
        known = [s for s in (row.last_seq, recorded, live.last_seq) if s is not None]
        log.warning("session %s: reopened in the engine from its checkpoint (seq %s)",
                    live.id, row.state_seq)
        await self._restore(live.spec, row.state, max(known, default=None))

    def release_for_reload(self, live: LiveSession) -> None:
        """The engine no longer holds the session: let it go here too, so that its next
        request reloads it from its checkpoint (numbering on after its last seq)."""
        with self._lock:
            if self._live.get(live.id) is live:
                del self._live[live.id]
                self._seq_floor[live.id] = live.last_seq

    def _read_row(self, session_id: uuid.UUID
                  ) -> tuple[LocalisationSession | None, int | None, bool]:
        with self.db_sessions() as db:
            row = db.get(LocalisationSession, session_id)
            if row is None:
                return None, None, False
            # On a shared engine other API processes hold the session too, and their queued
            # frames are theirs to answer (or to report when they start again).
            if not self.engine.shared and (n := store.interrupt_orphans(
                    db, session_id=session_id, owner=self.owner)):
                log.warning("session %s: %d frame(s) left queued by another server "
                            "reported interrupted", session_id, n)
            return (row, store.last_recorded_seq(db, session_id=session_id),
                    store.converged_since_start(db, session_id=session_id))

    # -- living and ending ------------------------------------------------------------------

    def forget(self, session_id: uuid.UUID, ending: dict = CLOSED) -> None:
        """Drop a deleted (or, with ``ending=EXPIRED``, expired) session: close it in the
        engine and end its streams with that message."""
        key = str(session_id)
        with self._lock:
            self._live.pop(key, None)
        self.on_forget(key)
        self.metrics.live_sessions.set(len(self._live))
        self.engine.close_session(key)
        self.loop.call_soon_threadsafe(self.hub.close_session, key, ending)

    def restart_convergence(self, live: LiveSession) -> None:
        """After a reset or an initial pose: the next estimates are initialising until one
        converges again."""
        live.converged = False

    def keep_alive(self, live: LiveSession) -> None:
        live.last_active = utcnow()

    async def keep_alive_stored(self, live: LiveSession) -> None:
        self.keep_alive(live)
        await asyncio.to_thread(self._write, store.keep_alive, uuid.UUID(live.id))

    async def expire(self, live: LiveSession) -> None:
        """Mark the session expired and release it: its worker drops the localiser, its
        streams close. Its record and poses stay readable."""
        session_id = uuid.UUID(live.id)
        await asyncio.to_thread(self._write, store.expire, session_id)
        self.forget(session_id, EXPIRED)
        log.info("session %s expired after %d s without activity", live.id, live.ttl_s)

    async def expire_idle(self) -> int:
        """Expire the live sessions past their time to live; how many."""
        idle = self.idle_expired()
        for live in idle:
            await self.expire(live)
        return len(idle)

    def idle_expired(self) -> list[LiveSession]:
        """Live sessions past their time to live with no frame in flight."""
        now = utcnow()
        return [live for live in self.held() if not live.arrivals and live.expired(now)]

    def pending(self, session_id: uuid.UUID) -> int:
        """The session's frames accepted here and not answered yet."""
        live = self._live.get(str(session_id))
        return len(live.arrivals) if live is not None else 0

    async def interrupted(self, live: LiveSession) -> list[dict]:
        """``frame_error`` messages (kind ``interrupted``) for the frames a stopped server
        left unanswered, each given once: the caller sends them on a stream."""
        frames = await asyncio.to_thread(self._take_interrupted, uuid.UUID(live.id))
        return [FrameError(session_id=live.id, seq=f.seq, captured_at=f.captured_at,
                           kind=f.error_kind, reason=f.error_reason, latency_ms=None)
                .model_dump(mode="json") for f in frames]

    def _take_interrupted(self, session_id: uuid.UUID) -> list:
        with self.db_sessions() as db:
            return store.take_interrupted(db, session_id=session_id)

    def _write(self, fn, session_id: uuid.UUID) -> None:
        with self.db_sessions() as db:
            fn(db, session_id=session_id)


def expired_problem(session_id) -> Problem:
    return Problem(410, f"session {session_id} expired after its time to live without a "
                   "frame or keep-alive; create a new session", kind=ProblemKind.SESSION_EXPIRED)
