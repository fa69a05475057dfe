"""Live sessions in the API process: frames in, outcomes stored, estimates published.

Threads and the loop:

- the event loop accepts frames: it numbers each (no awaits between the sequence check and
  the queueing, so two requests of one session cannot take the same number) and queues
  its record for the writer, and publishes messages;
- one writer thread (:mod:`app.sessions.writer`) stores, in batches and in order, the
  records of accepted frames (:class:`~app.sessions.models.Frame`) and the outcomes
  (poses, counters, checkpoints), then has the loop settle them. A frame goes to its worker only once its record is
  stored, so that a frame accepted by a server that then dies is reported after the
  restart and its ``seq`` never reused; a request is answered ``202`` only then too;
- the engine's reader thread hands each outcome to :meth:`SessionRuntime.on_outcome`, which
  turns it into its stream message, has the loop publish it at once and queues it for
  storage: the stream never waits for the database. A ``?wait=true`` request is answered
  only once its pose is stored, so what it returns can be read back; a pose the database
  refuses is reported as a ``frame_error`` of kind ``not_stored``.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
import uuid
from dataclasses import dataclass, field
from datetime import datetime

from sqlalchemy.orm import Session, sessionmaker

from app.config import Settings
from app.db import utcnow
from app.metrics import Metrics
from app.problems import Problem
from app.sessions import store
from app.sessions.admission import check_revision, next_seq, spec_for
from app.sessions.models import LocalisationSession
from app.sessions.schemas import FrameError, PoseEstimate
from app.sessions.store import FrameRecord, FrameStore, OutcomeRecord
from app.sessions.writer import Accepted, Barrier, Writer
from app.stream.hub import LocalHub
from workers.engine import (
    Checkpoint,
    EngineClosed,
    FrameDone,
    FrameFailed,
    LocalEngine,
    Outcome,
    SessionSpec,
    WorkerDied,
)

log = logging.getLogger(__name__)

OPEN_TIMEOUT_S = 120.0


@dataclass(slots=True)
class Arrival:
    t0: float
    """``time.perf_counter()`` when the frame arrived."""
    received_at: datetime
    captured_at: datetime | None
    data: bytes | None
    """The frame, until it goes to the engine."""
    queued: asyncio.Future
    """Resolves with the seq once the frame is recorded and queued in the engine."""
    previous_seq: int | None
    """The session's last seq before this frame: restored if the record fails."""


@dataclass(eq=False)
class LiveSession:
    id: str
    token_hash: str
    spec: SessionSpec
    last_seq: int | None
    """Highest sequence number accepted (processed, queued, or recorded before a restart)."""
    arrivals: dict[int, Arrival] = field(default_factory=dict)
    """Frames accepted and not yet answered, by sequence number."""


class SessionRuntime:
    def __init__(self, *, settings: Settings, db_sessions: sessionmaker[Session],
                 engine: LocalEngine, hub: LocalHub, metrics: Metrics) -> None:
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
        self._waiters: dict[tuple[str, int], asyncio.Future] = {}
        self._seq_floor: dict[str, int] = {}
        """Last seq of a live session dropped for a reload, until the reload reads it."""
        self._lock = threading.Lock()
        self._writer = Writer(self.store, metrics, self._settle)
        self._idle = asyncio.Event()
        self._closing = False

    # -- life cycle -------------------------------------------------------------------------

    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        self.loop = loop
        self._writer.start(loop)

    async def drain(self, timeout: float) -> None:
        """Refuse new frames, then wait (up to ``timeout``) until every accepted frame has
        been answered and stored."""
        self._closing = True
        deadline = time.monotonic() + timeout
        while self.pending_total() and time.monotonic() < deadline:
            self._idle.clear()
            try:
                await asyncio.wait_for(self._idle.wait(), max(deadline - time.monotonic(), 0))
            except TimeoutError:
                break

    def stop(self) -> None:
        """Store what the engine has reported; call after the engine has stopped."""
        self._writer.stop(30.0)

    def pending_total(self) -> int:
        return sum(len(live.arrivals) for live in list(self._live.values()))

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
        live = LiveSession(str(row.id), row.token_hash, spec, row.last_seq)
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
        row, recorded = await asyncio.to_thread(self._read_row, session_id)
        if row is None:
            return None
        spec = spec_for(row, self.settings)
        check_revision(spec)
        try:
            await asyncio.wrap_future(self.engine.open_session(spec, state=row.state))
        except Exception as exc:
            # The worker's message may name files under the data directory: logged only.
            log.warning("session %s could not be restored", spec.session_id, exc_info=exc)
            raise Problem(503, f"the session could not be restored ({type(exc).__name__}); "
                          "see the server log", kind="session-unavailable") from None
        # Never reuse a seq: the highest ever accepted, answered or not, counts.
        known = [s for s in (row.last_seq, recorded, self._seq_floor.pop(spec.session_id, None))
                 if s is not None]
        live = LiveSession(spec.session_id, row.token_hash, spec, max(known, default=None))
        with self._lock:
            self._live[live.id] = live
        self.metrics.live_sessions.set(len(self._live))
        return live

    def _read_row(self, session_id: uuid.UUID) -> tuple[LocalisationSession | None, int | None]:
        with self.db_sessions() as db:
            row = db.get(LocalisationSession, session_id)
            if row is None:
                return None, None
            if (n := store.interrupt_orphans(db, session_id=session_id, owner=self.owner)):
                log.warning("session %s: %d frame(s) left queued by another server "
                            "reported interrupted", session_id, n)
            return row, store.last_recorded_seq(db, session_id=session_id)

    def forget(self, session_id: uuid.UUID) -> None:
        """Drop a deleted session: close it in the engine and end its streams."""
        key = str(session_id)
        with self._lock:
            self._live.pop(key, None)
        self.metrics.live_sessions.set(len(self._live))
        self.engine.close_session(key)
        self.loop.call_soon_threadsafe(self.hub.close_session, key)

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

    def _take_interrupted(self, session_id: uuid.UUID) -> list:
        with self.db_sessions() as db:
            return store.take_interrupted(db, session_id=session_id)

    # -- frames (event loop) ----------------------------------------------------------------

    def accept(self, live: LiveSession, data: bytes, *, seq: int | None,
               captured_at: datetime | None, t0: float) -> tuple[int, asyncio.Future]:
        """Number a frame whose bytes passed the header checks and queue its record.

        Returns the frame's seq and a future that resolves (with the seq) once the frame is
        recorded and queued in the engine, or fails with a 503 :class:`Problem` when it
        could not be recorded (nothing was done with it then).

        Raises
        ------
        Problem
            409 for a duplicate, stale or exhausted ``seq``, 429 when the session has too
            many frames queued, 503 while the server shuts down.
        """
        if self._closing:
            raise Problem(503, "the server is shutting down; send the frame again later",
                          kind="shutting-down", headers={"Retry-After": "5"})
        seq = next_seq(live.last_seq, seq)
        if len(live.arrivals) >= self.settings.max_pending_frames:
            raise Problem(429, f"{len(live.arrivals)} frames of this session are still queued",
                          kind="too-many-pending", headers={"Retry-After": "1"})
        arrival = Arrival(t0, utcnow(), captured_at, data, self.loop.create_future(),
                          live.last_seq)
        live.arrivals[seq] = arrival
        live.last_seq = seq
        self._writer.put(Accepted(live, FrameRecord(live.id, seq, arrival.received_at,
                                                    captured_at)))
        self.metrics.frames_accepted.inc()
        return seq, arrival.queued

    async def queued_before(self) -> None:
        """Return once every frame accepted so far has gone to the engine (or failed), so
        that a control sent now runs after them."""
        done = self.loop.create_future()
        self._writer.put(Barrier(done))
        await done

    def waiter(self, live: LiveSession, seq: int) -> asyncio.Future:
        """A future for the frame's message (pose or frame_error); take it right after
        :meth:`accept`, before any await."""
        fut = self.loop.create_future()
        self._waiters[(live.id, seq)] = fut
        return fut

    def drop_waiter(self, live: LiveSession, seq: int) -> None:
        self._waiters.pop((live.id, seq), None)

    def _to_engine(self, item: Accepted, error: Exception | None) -> None:
        """Event loop: the frame's record is stored (or refused); hand it to its worker."""
        live, seq = item.live, item.record.seq
        arrival = live.arrivals.get(seq)
        if arrival is None:
            return
        if error is not None:
            del live.arrivals[seq]
            if live.last_seq == seq:
                live.last_seq = arrival.previous_seq
            _resolve(arrival.queued, exception=Problem(
                503, "the frame could not be recorded, so it was not processed; retry",
                kind="storage-unavailable", headers={"Retry-After": "1"}))
            return
        data, arrival.data = arrival.data, None
        captured = arrival.captured_at.timestamp() if arrival.captured_at is not None else None
        try:
            self.engine.submit_frame(live.id, seq, data, captured_at=captured)
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
        """Engine reader thread: publish the message now, store it later."""
        msg = self._message(outcome, time.perf_counter())
        if msg is not None and self.loop is not None and not self.loop.is_closed():
            self.loop.call_soon_threadsafe(self.hub.publish, msg[0], msg[2])
        self._writer.put(OutcomeRecord(outcome, msg[2] if msg is not None else None))

    def _message(self, outcome: Outcome, t_back: float) -> tuple[str, int, dict] | None:
        if isinstance(outcome, Checkpoint):
            return None
        live = self._live.get(outcome.session_id)
        arrival = live.arrivals.get(outcome.seq) if live is not None else None
        latency_ms = (t_back - arrival.t0) * 1e3 if arrival is not None else 0.0
        received = arrival.received_at if arrival is not None else utcnow()
        captured = arrival.captured_at if arrival is not None else None
        if isinstance(outcome, FrameDone):
            e = outcome.estimate
            msg = PoseEstimate(
                session_id=outcome.session_id, seq=outcome.seq, captured_at=captured,
                received_at=received, x=e["x"], y=e["y"], lat=e["lat"], lon=e["lon"],
                sigma_x=e["sigma_x"], sigma_y=e["sigma_y"], cov=list(e["cov"]),
                feature=e["feature"], next_feature=e["next_feature"],
                n_particles=e["n_particles"], status=e["status"],
                best_image=e.get("best_image", -1), decode_ms=outcome.decode_ms,
                processing_ms=e["processing_ms"],
                latency_ms=latency_ms)
        else:
            msg = FrameError(session_id=outcome.session_id, seq=outcome.seq,
                             captured_at=captured, kind=outcome.kind, reason=outcome.reason,
                             latency_ms=latency_ms)
        return outcome.session_id, outcome.seq, msg.model_dump(mode="json")

    def _settle(self, done: list[tuple[object, Exception | None]]) -> None:
        """Event loop: the items are stored (or refused). Frames go to the engine; answered
        frames wake their waiters and leave the arrivals."""
        for item, error in done:
            if isinstance(item, Accepted):
                self._to_engine(item, error)
            elif isinstance(item, Barrier):
                _resolve(item.done, None)
            elif item.message is not None:
                session_id, seq, msg = item.outcome.session_id, item.outcome.seq, item.message
                if error is not None:
                    self.hub.publish(session_id, msg)  # the not_stored report
                live = self._live.get(session_id)
                if live is not None:
                    live.arrivals.pop(seq, None)
                fut = self._waiters.pop((session_id, seq), None)
                if fut is not None and not fut.done():
                    fut.set_result(msg)
        if not self.pending_total():
            self._idle.set()


def _resolve(fut: asyncio.Future, value=None, *, exception: BaseException | None = None) -> None:
    """Settle a future nobody may be waiting on any more (its request was cancelled)."""
    if fut.done():
        return
    if exception is not None:
        fut.set_exception(exception)
        fut.exception()  # retrieved: a WebSocket frame's refusal is reported elsewhere
    else:
        fut.set_result(value)
