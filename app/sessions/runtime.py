"""Live sessions in the API process: frames in, outcomes stored, estimates published.

The parts, and the threads and loop they run on:

- intake (this module, the event loop): sessions opened, reloaded and expired; frames
  numbered (no awaits between the sequence check and the queueing, so two requests of one
  session cannot take the same number, or by the shared engine across API processes) and
  their records queued for the writer; controls run after the frames before them;
- storage (:mod:`app.sessions.writer`, one thread, over :mod:`app.sessions.store`): the
  records of accepted frames and the outcomes (poses, counters, checkpoints), stored in
  batches and in order, then settled on the loop. A frame goes to its worker only once its
  record is stored, so that a frame accepted by a server that then dies is reported after
  the restart and its ``seq`` never reused; a request is answered ``202`` only then too;
- outcomes (:mod:`app.sessions.outcomes`, from the engine's reader thread): each outcome
  becomes its message, published at once (the stream never waits for the database) and
  stored; a ``?wait=true`` request is answered only once its pose is stored, so what it
  returns can be read back; a pose the database refuses is reported as a ``frame_error``
  of kind ``not_stored``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
import time
import uuid
from dataclasses import replace
from datetime import datetime

from sqlalchemy.orm import Session, sessionmaker

from vloc.app.config import Settings
from vloc.app.db import utcnow
from vloc.app.engine import (
    Engine,
    EngineClosed,
    FrameFailed,
    Outcome,
    SeqRefused,
    SessionSpec,
    WorkerDied,
)
from vloc.app.metrics import Metrics
from vloc.app.problems import Problem, ProblemKind
from vloc.app.sessions import store
from vloc.app.sessions.admission import check_revision, next_seq, spec_for
from vloc.app.sessions.budget import FrameBudget, Held
from vloc.app.sessions.live import LAST_FRAME_MAX_BYTES, Arrival, LiveSession
from vloc.app.sessions.models import LocalisationSession
from vloc.app.sessions.outcomes import Outcomes
from vloc.app.sessions.schemas import MAX_SEQ, FrameError
from vloc.app.sessions.store import FrameRecord, FrameStore
from vloc.app.sessions.writer import Accepted, Barrier, Writer
from vloc.app.stream.hub import CLOSED, EXPIRED, LocalHub

log = logging.getLogger(__name__)

OPEN_TIMEOUT_S = 120.0
DRAIN_STALL_S = 10.0
"""A drain gives up once no frame has been answered for this long."""
DRAIN_POLL_S = 0.5
GONE_AFTER_S = 3.0
"""A shared engine's API process whose lease no shard has seen renewed for this long is
gone: the frames it left queued are settled by the processes still alive."""


class SessionRuntime:
    def __init__(self, *, settings: Settings, db_sessions: sessionmaker[Session],
                 engine: Engine, hub: LocalHub, metrics: Metrics) -> None:
        self.settings = settings
        self.db_sessions = db_sessions
        self.engine = engine
        self.hub = hub
        self.metrics = metrics
        self.owner = settings.instance_name
        self.store = FrameStore(db_sessions, owner=self.owner)
        self.loop: asyncio.AbstractEventLoop | None = None
        self._live: dict[str, LiveSession] = {}
        self._opening: dict[str, asyncio.Future] = {}
        self._current: dict[str, int] = {}
        """The current revision of the maps of live sessions that follow their map, as
        this process last heard (:meth:`map_revised`, :meth:`follow_maps`)."""
        self._seq_floor: dict[str, int] = {}
        """Last seq of a live session dropped for a reload, until the reload reads it."""
        self._lock = threading.Lock()
        self._writer = Writer(self.store, metrics, self._settle)
        self.outcomes = Outcomes(settings=settings, hub=hub, writer=self._writer,
                                 live=self._live.get)
        self._idle = asyncio.Event()
        self._closing = False
        self.budget = FrameBudget(max_bytes=settings.max_queued_bytes,
                                  max_frames=settings.max_queued_frames,
                                  accepted=self._accepted_held)

    # -- life cycle -------------------------------------------------------------------------

    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        self.loop = self.outcomes.loop = loop
        self._writer.start(loop)

    async def drain(self, timeout: float, *, stall_s: float = DRAIN_STALL_S) -> None:
        """Refuse new frames, then wait until every accepted frame has been answered and
        stored: as long as the backlog keeps shrinking, up to ``timeout`` in all, and no
        more than ``stall_s`` after the last frame answered (an engine that answers
        nothing more is not waited for)."""
        self._closing = True
        now = time.monotonic()
        deadline, progress, left = now + timeout, now, self.pending_total()
        while left and now < deadline and now - progress < stall_s:
            self._idle.clear()
            wake = min(deadline, progress + stall_s, now + DRAIN_POLL_S)
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._idle.wait(), max(wake - now, 0))
            now, before, left = time.monotonic(), left, self.pending_total()
            if left < before:
                progress = now
        if (n := self.outcomes.flush_checkpoints()):
            log.info("stored the latest checkpoints of %d session(s)", n)

    def stop(self) -> None:
        """Store what the engine has reported; call after the engine has stopped."""
        self._writer.stop(30.0)

    def pending_total(self) -> int:
        return sum(len(live.arrivals) for live in list(self._live.values()))

    def _accepted_held(self) -> dict[str, Held]:
        """The frames accepted and not answered, by session (for :attr:`budget`)."""
        return {live.id: Held(len(live.arrivals), sum(a.size for a in live.arrivals.values()))
                for live in list(self._live.values()) if live.arrivals}

    # -- sessions ---------------------------------------------------------------------------

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
        live = LiveSession(str(row.id), row.token_hash, spec, row.last_seq,
                           ttl_s=row.ttl_s, last_active=row.last_active_at or utcnow(),
                           follows_map=row.follows_map)
        with self._lock:
            self._live[live.id] = live
        self.metrics.live_sessions.set(len(self._live))
        return live

    async def get(self, session_id: uuid.UUID) -> LiveSession | None:
        """The live session, loaded from its checkpoint when this process does not hold it.

        None when the session does not exist.
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
        live = LiveSession(spec.session_id, row.token_hash, spec, last_seq,
                           converged=converged, ttl_s=row.ttl_s,
                           last_active=row.last_active_at or row.created_at,
                           follows_map=row.follows_map)
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

    async def _reopen(self, live: LiveSession) -> None:
        """The engine lost the session (its actor died and came back empty): open it again
        from the checkpoint in the database."""
        row, recorded, _ = await asyncio.to_thread(self._read_row, uuid.UUID(live.id))
        if row is None:
            raise Problem(404, f"session {live.id} was deleted", kind=ProblemKind.NOT_FOUND)
        known = [s for s in (row.last_seq, recorded, live.last_seq) if s is not None]
        log.warning("session %s: reopened in the engine from its checkpoint (seq %s)",
                    live.id, row.state_seq)
        await self._restore(live.spec, row.state, max(known, default=None))

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

    def forget(self, session_id: uuid.UUID, ending: dict = CLOSED) -> None:
        """Drop a deleted (or, with ``ending=EXPIRED``, expired) session: close it in the
        engine and end its streams with that message."""
        key = str(session_id)
        with self._lock:
            self._live.pop(key, None)
        self.outcomes.forget(key)
        self.metrics.live_sessions.set(len(self._live))
        self.engine.close_session(key)
        self.loop.call_soon_threadsafe(self.hub.close_session, key, ending)

    def restart_convergence(self, live: LiveSession) -> None:
        """After a reset or an initial pose: the next estimates are initialising until one
        converges again."""
        live.converged = False

    def keep_alive(self, live: LiveSession) -> None:
        live.last_active = utcnow()

    async def expire(self, live: LiveSession) -> None:
        """Mark the session expired and release it: its worker drops the localiser, its
        streams close. Its record and poses stay readable."""
        session_id = uuid.UUID(live.id)
        await asyncio.to_thread(self._write, store.expire, session_id)
        self.forget(session_id, EXPIRED)
        log.info("session %s expired after %d s without activity", live.id, live.ttl_s)

    async def keep_alive_stored(self, live: LiveSession) -> None:
        self.keep_alive(live)
        await asyncio.to_thread(self._write, store.keep_alive, uuid.UUID(live.id))

    async def expire_idle(self) -> int:
        """Expire the live sessions past their time to live; how many."""
        idle = self.idle_expired()
        for live in idle:
            await self.expire(live)
        return len(idle)

    def _write(self, fn, session_id: uuid.UUID) -> None:
        with self.db_sessions() as db:
            fn(db, session_id=session_id)

    def idle_expired(self) -> list[LiveSession]:
        """Live sessions past their time to live with no frame in flight."""
        now = utcnow()
        return [live for live in list(self._live.values())
                if not live.arrivals and live.expired(now)]

    def pending(self, session_id: uuid.UUID) -> int:
        live = self._live.get(str(session_id))
        return len(live.arrivals) if live is not None else 0

    async def interrupted(self, live: LiveSession) -> list[dict]:
        """``frame_error`` messages (kind ``interrupted``) for the frames a stopped server
        left unanswered, each given once: the caller sends them on a stream."""
        frames = await asyncio.to_thread(self._take_interrupted, uuid.UUID(live.id))
        return [FrameError(session_id=live.id, seq=f.seq, captured_at=f.captured_at,
                           kind=f.error_kind, reason=f.error_reason, latency_ms=None)
                .model_dump(mode="json") for f in frames]

    async def settle_gone(self) -> int:
        """Shared engine: report the frames that API processes no longer alive left queued
        (failed, kind ``interrupted``, published to their sessions' streams); how many."""
        alive = await asyncio.to_thread(self.engine.live_instances, GONE_AFTER_S)
        if alive is None:
            return 0
        frames = await asyncio.to_thread(self._settle_gone, alive | {self.owner})
        for f in frames:
            self.hub.publish(str(f.session_id), FrameError(
                session_id=f.session_id, seq=f.seq, captured_at=f.captured_at,
                kind=f.error_kind, reason=f.error_reason, latency_ms=None)
                .model_dump(mode="json"))
        if frames:
            log.warning("%d frame(s) left queued by API processes no longer alive reported "
                        "interrupted", len(frames))
        return len(frames)

    def _settle_gone(self, alive: set[str]) -> list:
        with self.db_sessions() as db:
            return store.settle_gone(db, alive=alive)

    def _take_interrupted(self, session_id: uuid.UUID) -> list:
        with self.db_sessions() as db:
            return store.take_interrupted(db, session_id=session_id)

    # -- sessions following their map ---------------------------------------------------------

    def map_revised(self, map_id: str, revision: int) -> None:
        """The map's current revision changed (built, or restored) in this process: its
        sessions that follow it move before their next frame (:meth:`follow`). Callable
        from any thread."""
        with self._lock:
            self._current[str(map_id)] = int(revision)
        if self.loop is not None and not self.loop.is_closed():
            self.loop.call_soon_threadsafe(self._spawn_moves, str(map_id))

    def _spawn_moves(self, map_id: str) -> None:
        """Event loop: move the idle following sessions of the map now (the busy ones
        move at their next frame, or here once a frame has gone)."""
        for live in list(self._live.values()):
            if live.spec.map_id == map_id and self._behind(live) is not None:
                task = self.loop.create_task(self.follow(live), name=f"follow-{live.id}")
                task.add_done_callback(_log_failure)

    async def follow_maps(self) -> int:
        """Read the current revision of the maps that live sessions follow (another API
        process may have built or restored them) and move those sessions; how many
        moved."""
        maps = {live.spec.map_id for live in list(self._live.values()) if live.follows_map}
        if not maps:
            return 0
        current = await asyncio.to_thread(self._read_revisions, maps)
        with self._lock:
            self._current.update(current)
        moved = 0
        for live in list(self._live.values()):
            if self._behind(live) is not None:
                moved += await self.follow(live)
        return moved

    def _read_revisions(self, maps: set[str]) -> dict[str, int]:
        from sqlalchemy import select

        from vloc.app.maps.models import Map

        with self.db_sessions() as db:
            rows = db.execute(select(Map.id, Map.revision).where(
                Map.id.in_([uuid.UUID(m) for m in maps]))).all()
        return {str(i): int(r) for i, r in rows if r}

    def _behind(self, live: LiveSession) -> int | None:
        """The revision a following session should move to, or None."""
        if not live.follows_map:
            return None
        current = self._current.get(live.spec.map_id)
        if current is None or current in (live.spec.revision, live.refused_revision):
            return None
        return current

    async def follow(self, live: LiveSession) -> bool:
        """Move a session that follows its map to the map's current revision, between two
        frames: every frame accepted before runs on the old revision, every frame after
        on the new one (the engine's worker carries the filter's state across,
        :meth:`workers.core.localisers.base.Localiser.set_state`). Whether it moved; a
        revision it cannot move to (its files gone, a localiser that cannot move) is
        logged and not tried again, and the session goes on where it is."""
        while live.moving is not None:
            await asyncio.shield(live.moving)
        revision = self._behind(live)
        if revision is None:
            return False
        live.moving = self.loop.create_future()
        try:
            return await self._move(live, revision)
        finally:
            live.moving.set_result(None)
            live.moving = None

    async def _move(self, live: LiveSession, revision: int) -> bool:
        spec = replace(live.spec, revision=revision, map_folder=str(
            self.settings.packed_map_dir(live.spec.map_id, revision)))
        try:
            check_revision(spec)
            await self.control(live, "move", spec=spec)
        except Exception as exc:  # noqa: BLE001 - the session stays where it is
            live.refused_revision = revision
            self.metrics.session_moves.labels("failed").inc()
            log.warning("session %s stays on map revision %d: moving to %d failed (%s)",
                        live.id, live.spec.revision, revision, exc)
            return False
        previous, live.spec = live.spec.revision, spec
        self.metrics.session_moves.labels("moved").inc()
        await asyncio.to_thread(self._write_revision, uuid.UUID(live.id), revision)
        log.info("session %s moved from map revision %d to %d", live.id, previous, revision)
        return True

    def _write_revision(self, session_id: uuid.UUID, revision: int) -> None:
        from sqlalchemy import update

        with self.db_sessions() as db:
            db.execute(update(LocalisationSession)
                       .where(LocalisationSession.id == session_id)
                       .values(map_revision=revision))
            db.commit()

    # -- frames (event loop) ----------------------------------------------------------------

    async def accept(self, live: LiveSession, data: bytes, *, seq: int | None,
                     captured_at: datetime | None, t0: float,
                     metadata: dict | None = None,
                     admitted: bool = False) -> tuple[int, asyncio.Future]:
        """Number a frame whose bytes passed the header checks and queue its record.

        Returns the frame's seq and a future that resolves (with the seq) once the frame is
        recorded and queued in the engine, or fails with a 503 :class:`Problem` when it
        could not be recorded (nothing was done with it then).

        A local engine's frames are numbered here, with no await between the sequence
        check and the queueing; a shared engine numbers them itself, across API processes.

        ``admitted``: the frame's body was let in by :attr:`budget` already.

        Raises
        ------
        Problem
            409 for a duplicate, stale or exhausted ``seq``, 429 when the session has too
            many frames queued or more than its share of the server's, 503 while the server
            shuts down or when it holds as many frames as it takes.
        """
        if self._closing:
            raise Problem(503, "the server is shutting down; send the frame again later",
                          kind=ProblemKind.SHUTTING_DOWN, headers={"Retry-After": "5"})
        if live.moving is not None or self._behind(live) is not None:
            # the map has a new revision: this frame and the next run on it
            await self.follow(live)
        if not self.engine.shared:
            seq = next_seq(live.last_seq, seq)
        if len(live.arrivals) >= self.settings.max_pending_frames:
            raise Problem(429, f"{len(live.arrivals)} frames of this session are still queued",
                          kind=ProblemKind.TOO_MANY_PENDING, headers={"Retry-After": "1"})
        if not admitted:
            self.budget.check(live.id, len(data))
        if self.engine.shared:
            seq = await self._reserve(live, seq)
        arrival = Arrival(t0, utcnow(), captured_at, data, self.loop.create_future(),
                          live.last_seq, metadata or None, len(data))
        live.arrivals[seq] = arrival
        live.last_seq = seq if live.last_seq is None else max(live.last_seq, seq)
        live.last_active = arrival.received_at
        live.last_frame = (seq, data) if len(data) <= LAST_FRAME_MAX_BYTES else None
        self._writer.put(Accepted(live, FrameRecord(live.id, seq, arrival.received_at,
                                                    captured_at)))
        self.metrics.frames_accepted.inc()
        return seq, arrival.queued

    async def _reserve(self, live: LiveSession, seq: int | None) -> int:
        """The frame's seq from the shared engine, which numbers the session's frames for
        every API process; the session is reopened from its checkpoint once when the
        engine no longer holds it."""
        for attempt in range(2):
            try:
                got = await asyncio.wrap_future(self.engine.reserve_seq(live.id, seq))
            except SeqRefused as exc:
                raise Problem(409, str(exc), kind=ProblemKind(exc.kind), last_seq=exc.last_seq) from None
            except KeyError:
                if attempt:
                    raise Problem(503, "the engine could not reopen the session; retry",
                                  kind=ProblemKind.SESSION_UNAVAILABLE,
                                  headers={"Retry-After": "1"}) from None
                await self._reopen(live)
                continue
            except (EngineClosed, WorkerDied) as exc:
                raise Problem(503, f"the engine could not take the frame: {exc}",
                              kind=ProblemKind.ENGINE_UNAVAILABLE, headers={"Retry-After": "1"}) from None
            if got > MAX_SEQ:
                self.engine.release_seq(live.id, got)
                raise Problem(409, f"the session has used every seq up to {MAX_SEQ}",
                              kind=ProblemKind.SEQ_EXHAUSTED, last_seq=MAX_SEQ)
            return got
        raise AssertionError("unreachable")

    async def control(self, live: LiveSession, op: str, **kwargs) -> object:
        """Run a control on the session's localiser after the frames already accepted.

        Raises ValueError for a control the localiser refuses; KeyError, EngineClosed or
        WorkerDied when the engine cannot run it.
        """
        await self.queued_before()
        try:
            return await asyncio.wrap_future(self.engine.control(live.id, op, **kwargs))
        except KeyError:
            if not self.engine.shared:
                raise
        await self._reopen(live)
        return await asyncio.wrap_future(self.engine.control(live.id, op, **kwargs))

    async def queued_before(self) -> None:
        """Return once every frame accepted so far has gone to the engine (or failed), so
        that a control sent now runs after them."""
        done = self.loop.create_future()
        self._writer.put(Barrier(done))
        await done

    def waiter(self, live: LiveSession, seq: int) -> asyncio.Future:
        """A future for the frame's message (pose or frame_error); take it right after
        :meth:`accept`, before any await."""
        return self.outcomes.waiter(live.id, seq)

    def drop_waiter(self, live: LiveSession, seq: int) -> None:
        self.outcomes.drop_waiter(live.id, seq)

    def _to_engine(self, item: Accepted, error: Exception | None) -> None:
        """Event loop: the frame's record is stored (or refused); hand it to its worker."""
        live, seq = item.live, item.record.seq
        arrival = live.arrivals.get(seq)
        if arrival is None:
            return
        if error is not None:
            del live.arrivals[seq]
            if self.engine.shared:
                self.engine.release_seq(live.id, seq)
            elif live.last_seq == seq:
                live.last_seq = arrival.previous_seq
            _resolve(arrival.queued, exception=Problem(
                503, "the frame could not be recorded, so it was not processed; retry",
                kind=ProblemKind.STORAGE_UNAVAILABLE, headers={"Retry-After": "1"}))
            return
        data, arrival.data = arrival.data, None
        captured = arrival.captured_at.timestamp() if arrival.captured_at is not None else None
        try:
            self.engine.submit_frame(live.id, seq, data, captured_at=captured,
                                     metadata=arrival.metadata)
        except (KeyError, EngineClosed, WorkerDied) as exc:
            if isinstance(exc, KeyError):
                with self._lock:
                    # Reloaded from its checkpoint on the next request.
                    if self._live.get(live.id) is live:
                        del self._live[live.id]
                        self._seq_floor[live.id] = live.last_seq
            kind = "worker_died" if isinstance(exc, WorkerDied) else "not_open"
            self.on_outcome(FrameFailed(live.id, seq, kind,
                                        f"the engine could not take the frame: {exc}"))
        _resolve(arrival.queued, seq)

    # -- outcomes ---------------------------------------------------------------------------

    def on_outcome(self, outcome: Outcome) -> None:
        """Engine reader thread: see :meth:`Outcomes.on_outcome`."""
        self.outcomes.on_outcome(outcome)

    def _settle(self, done: list[tuple[object, Exception | None]]) -> None:
        """Event loop: the items are stored (or refused). Frames go to the engine; answered
        frames wake their waiters and leave the arrivals."""
        for item, error in done:
            if isinstance(item, Accepted):
                self._to_engine(item, error)
            elif isinstance(item, Barrier):
                _resolve(item.done, None)
            else:
                self.outcomes.settle(item, error)
        if not self.pending_total():
            self._idle.set()


def expired_problem(session_id) -> Problem:
    return Problem(410, f"session {session_id} expired after its time to live without a "
                   "frame or keep-alive; create a new session", kind=ProblemKind.SESSION_EXPIRED)


def _resolve(fut: asyncio.Future, value=None, *, exception: BaseException | None = None) -> None:
    """Settle a future nobody may be waiting on any more (its request was cancelled)."""
    if fut.done():
        return
    if exception is not None:
        fut.set_exception(exception)
        fut.exception()  # retrieved: a WebSocket frame's refusal is reported elsewhere
    else:
        fut.set_result(value)


def _log_failure(task: asyncio.Task) -> None:
    if not task.cancelled() and task.exception() is not None:
        log.error("moving a session to its map's new revision failed",
                  exc_info=task.exception())
