"""Live sessions in the API process: frames in, outcomes stored, estimates published.

Threads and the loop:

- the event loop accepts frames (no awaits between the sequence check and the submission,
  so two requests of one session cannot take the same number) and publishes messages;
- the engine's reader thread hands each outcome to :meth:`SessionRuntime.on_outcome`, which
  turns it into its stream message, has the loop publish it at once and queues it for
  storage: the stream never waits for the database;
- one writer thread stores outcomes in batches (poses, counters, checkpoints) and then has
  the loop settle them: a ``?wait=true`` request is answered only once its pose is stored,
  so what it returns can be read back.
"""

from __future__ import annotations

import asyncio
import logging
import queue
import threading
import time
import uuid
from collections import defaultdict
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

from sqlalchemy.orm import Session, sessionmaker

from app.config import Settings
from app.db import utcnow
from app.metrics import Metrics
from app.problems import Problem
from app.sessions.models import LocalisationSession, Pose
from app.sessions.schemas import FrameError, PoseEstimate
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

_STOP = object()
_BATCH = 512
OPEN_TIMEOUT_S = 120.0


@dataclass(slots=True)
class Arrival:
    t0: float
    """``time.perf_counter()`` when the frame arrived."""
    received_at: datetime
    captured_at: datetime | None


@dataclass(eq=False)
class LiveSession:
    id: str
    token_hash: str
    spec: SessionSpec
    last_seq: int | None
    """Highest sequence number accepted (processed or still queued)."""
    arrivals: dict[int, Arrival] = field(default_factory=dict)
    """Frames accepted and not yet answered, by sequence number."""


def spec_for(row: LocalisationSession, settings: Settings) -> SessionSpec:
    folder = settings.packed_map_dir(str(row.map_id), row.map_revision)
    return SessionSpec(session_id=str(row.id), map_id=str(row.map_id),
                       revision=row.map_revision, map_folder=str(folder), mode=row.mode,
                       params=dict(row.params), seed=int(row.seed))


def check_revision(spec: SessionSpec) -> None:
    """503 ``map-revision-missing`` (naming the map, not the data path) when the packed
    revision a session needs is gone from the data directory."""
    if not Path(spec.map_folder).is_dir():
        raise revision_missing(spec.map_id, spec.revision)


def revision_missing(map_id: str, revision: int) -> Problem:
    return Problem(503, f"the files of map {map_id} revision {revision} are missing from "
                   "the data directory; restore them or rebuild the map",
                   kind="map-revision-missing")


class SessionRuntime:
    def __init__(self, *, settings: Settings, db_sessions: sessionmaker[Session],
                 engine: LocalEngine, hub: LocalHub, metrics: Metrics) -> None:
        self.settings = settings
        self.db_sessions = db_sessions
        self.engine = engine
        self.hub = hub
        self.metrics = metrics
        self.loop: asyncio.AbstractEventLoop | None = None
        self._live: dict[str, LiveSession] = {}
        self._opening: dict[str, asyncio.Future] = {}
        self._waiters: dict[tuple[str, int], asyncio.Future] = {}
        self._lock = threading.Lock()
        self._outcomes: queue.SimpleQueue = queue.SimpleQueue()
        self._writer: threading.Thread | None = None
        self._idle = asyncio.Event()

    # -- life cycle -------------------------------------------------------------------------

    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        self.loop = loop
        self._writer = threading.Thread(target=self._write_loop, name="pose-writer",
                                        daemon=True)
        self._writer.start()

    async def drain(self, timeout: float) -> None:
        """Wait (up to ``timeout``) until every accepted frame has been answered."""
        deadline = time.monotonic() + timeout
        while self.pending_total() and time.monotonic() < deadline:
            self._idle.clear()
            try:
                await asyncio.wait_for(self._idle.wait(), max(deadline - time.monotonic(), 0))
            except TimeoutError:
                break

    def stop(self) -> None:
        """Store what the engine has reported; call after the engine has stopped."""
        if self._writer is not None:
            self._outcomes.put(_STOP)
            self._writer.join(30.0)

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
        row = await asyncio.to_thread(self._read_row, session_id)
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
        live = LiveSession(spec.session_id, row.token_hash, spec, row.last_seq)
        with self._lock:
            self._live[live.id] = live
        self.metrics.live_sessions.set(len(self._live))
        return live

    def _read_row(self, session_id: uuid.UUID) -> LocalisationSession | None:
        with self.db_sessions() as db:
            return db.get(LocalisationSession, session_id)

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

    # -- frames (event loop) ----------------------------------------------------------------

    def accept(self, live: LiveSession, data: bytes, *, seq: int | None,
               captured_at: datetime | None, t0: float) -> int:
        """Number and queue a frame whose bytes passed the header checks.

        Raises
        ------
        Problem
            409 for a duplicate or stale ``seq``, 429 when the session has too many frames
            queued, 503 when the engine cannot take it.
        """
        if seq is None:
            seq = 0 if live.last_seq is None else live.last_seq + 1
        elif live.last_seq is not None and seq <= live.last_seq:
            kind = "duplicate-seq" if seq == live.last_seq else "stale-seq"
            raise Problem(409, f"seq {seq} is not after the last accepted seq {live.last_seq}",
                          kind=kind, last_seq=live.last_seq)
        if len(live.arrivals) >= self.settings.max_pending_frames:
            raise Problem(429, f"{len(live.arrivals)} frames of this session are still queued",
                          kind="too-many-pending", headers={"Retry-After": "1"})
        captured = captured_at.timestamp() if captured_at is not None else None
        live.arrivals[seq] = Arrival(t0, utcnow(), captured_at)
        try:
            self.engine.submit_frame(live.id, seq, data, captured_at=captured)
        except (KeyError, EngineClosed, WorkerDied) as exc:
            del live.arrivals[seq]
            with self._lock:
                # Reloaded from its checkpoint on the next request.
                self._live.pop(live.id, None)
            raise Problem(503, f"the session is not available in the engine ({exc}); retry",
                          kind="session-unavailable", headers={"Retry-After": "1"}) from None
        live.last_seq = seq
        self.metrics.frames_accepted.inc()
        return seq

    def waiter(self, live: LiveSession, seq: int) -> asyncio.Future:
        """A future for the frame's message (pose or frame_error); take it right after
        :meth:`accept`, before any await."""
        fut = self.loop.create_future()
        self._waiters[(live.id, seq)] = fut
        return fut

    def drop_waiter(self, live: LiveSession, seq: int) -> None:
        self._waiters.pop((live.id, seq), None)

    # -- outcomes ---------------------------------------------------------------------------

    def on_outcome(self, outcome: Outcome) -> None:
        """Engine reader thread: publish the message now, store it later."""
        msg = self._message(outcome, time.perf_counter())
        if msg is not None and self.loop is not None and not self.loop.is_closed():
            self.loop.call_soon_threadsafe(self.hub.publish, msg[0], msg[2])
        self._outcomes.put((outcome, msg))

    def _write_loop(self) -> None:
        while True:
            item = self._outcomes.get()
            stop = item is _STOP
            batch = [] if stop else [item]
            while len(batch) < _BATCH:
                try:
                    nxt = self._outcomes.get_nowait()
                except queue.Empty:
                    break
                if nxt is _STOP:
                    stop = True
                    break
                batch.append(nxt)
            if batch:
                try:
                    self._store(batch)
                except Exception:  # noqa: BLE001 - keep writing later outcomes
                    log.exception("storing %d outcomes failed", len(batch))
                messages = [m for _, m in batch if m is not None]
                if self.loop is not None and not self.loop.is_closed():
                    self.loop.call_soon_threadsafe(self._settle, messages)
            if stop:
                return

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

    def _store(self, batch: list[tuple[Outcome, tuple | None]]) -> None:
        by_session: dict[str, list[tuple[Outcome, tuple | None]]] = defaultdict(list)
        for outcome, msg in batch:
            by_session[outcome.session_id].append((outcome, msg))
        with self.db_sessions() as db:
            for session_id, items in by_session.items():
                row = db.get(LocalisationSession, uuid.UUID(session_id))
                if row is None:
                    continue  # deleted meanwhile
                for outcome, msg in items:
                    self._apply(db, row, outcome, msg[2] if msg else None)
            db.commit()
        for _, _, m in (msg for _, msg in batch if msg is not None):
            if m["type"] == "pose":
                self.metrics.frames_processed.labels(m["feature"]).inc()
                self.metrics.step_seconds.labels(m["feature"]).observe(m["processing_ms"] / 1e3)
                self.metrics.frame_latency.observe(m["latency_ms"] / 1e3)
            else:
                self.metrics.frames_failed.labels(m["kind"]).inc()

    @staticmethod
    def _apply(db: Session, row: LocalisationSession, outcome: Outcome, msg: dict | None) -> None:
        if isinstance(outcome, Checkpoint):
            row.state = outcome.state
            return
        row.last_seq = outcome.seq if row.last_seq is None else max(row.last_seq, outcome.seq)
        if isinstance(outcome, FrameFailed):
            row.frames_failed += 1
            return
        row.frames_processed += 1
        if outcome.state is not None:
            row.state, row.state_seq = outcome.state, outcome.seq
        cov = msg["cov"]
        db.add(Pose(session_id=row.id, seq=outcome.seq,
                    captured_at=datetime.fromisoformat(msg["captured_at"])
                    if msg["captured_at"] else None,
                    received_at=datetime.fromisoformat(msg["received_at"]),
                    x=msg["x"], y=msg["y"], lat=msg["lat"], lon=msg["lon"],
                    sigma_x=msg["sigma_x"], sigma_y=msg["sigma_y"], cov_xx=cov[0],
                    cov_xy=cov[1], cov_yx=cov[2], cov_yy=cov[3], feature=msg["feature"],
                    next_feature=msg["next_feature"], n_particles=msg["n_particles"],
                    status=msg["status"], best_image=msg["best_image"],
                    decode_ms=msg["decode_ms"], processing_ms=msg["processing_ms"],
                    latency_ms=msg["latency_ms"]))

    def _settle(self, messages: list[tuple[str, int, dict]]) -> None:
        """Event loop: the frames are stored; wake their waiters, forget their arrivals."""
        for session_id, seq, msg in messages:
            live = self._live.get(session_id)
            if live is not None:
                live.arrivals.pop(seq, None)
            fut = self._waiters.pop((session_id, seq), None)
            if fut is not None and not fut.done():
                fut.set_result(msg)
        if not self.pending_total():
            self._idle.set()
