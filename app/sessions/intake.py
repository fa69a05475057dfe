"""Frames in, outcomes stored, estimates published: one API process's frame intake.

Every frame goes through :meth:`FrameIntake.accept`, whichever transport brought it (an
HTTP ``POST .../frames`` or a WebSocket binary message), and every control through
:meth:`FrameIntake.control`. The parts, and the threads and loop they run on:

- intake (this module, the event loop): frames numbered (no awaits between the sequence
  check and the queueing, so two requests of one session cannot take the same number, or by
  the shared engine across API processes) and their records queued for the writer; controls
  run after the frames before them; a session behind its map moves first
  (:mod:`app.sessions.following`);
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

Which sessions this process holds, and their life cycle, is :mod:`app.sessions.registry`.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from datetime import datetime

from vloc.app.db import utcnow
from vloc.app.engine import (
    EngineClosed,
    FrameFailed,
    SeqRefused,
    WorkerDied,
)
from vloc.app.imagecheck import ImageHeader
from vloc.app.problems import Problem, ProblemKind
from vloc.app.sessions import store
from vloc.app.sessions.admission import next_seq
from vloc.app.sessions.budget import FrameBudget, Held
from vloc.app.sessions.following import MapFollowing
from vloc.app.sessions.live import LAST_FRAME_MAX_BYTES, Arrival, LiveSession
from vloc.app.sessions.outcomes import Outcomes
from vloc.app.sessions.registry import SessionRegistry
from vloc.app.sessions.schemas import MAX_SEQ, FrameError
from vloc.app.sessions.store import FrameRecord, FrameStore
from vloc.app.sessions.writer import Accepted, Barrier, Writer
from vloc.workers.core.metadata import FrameMetadata

log = logging.getLogger(__name__)

DRAIN_STALL_S = 10.0
"""A drain gives up once no frame has been answered for this long."""
DRAIN_POLL_S = 0.5
GONE_AFTER_S = 3.0
"""A shared engine's API process whose lease no shard has seen renewed for this long is
gone: the frames it left queued are settled by the processes still alive."""


class FrameIntake:
    """The frames and controls of the sessions in ``sessions``, from arrival to answer.

    It works with the registry's settings, database, engine, fan-out and metrics; it makes
    :attr:`following` (the sessions' moves run as its controls) and tells ``sessions`` to
    drop a forgotten session's outcomes state.
    """

    def __init__(self, sessions: SessionRegistry) -> None:
        self.sessions = sessions
        settings = self.settings = sessions.settings
        self.db_sessions = sessions.db_sessions
        self.engine, self.hub, self.metrics = sessions.engine, sessions.hub, sessions.metrics
        self.store = FrameStore(self.db_sessions, owner=sessions.owner)
        self.loop: asyncio.AbstractEventLoop | None = None
        self._writer = Writer(self.store, self.metrics, self._settle)
        self.outcomes = Outcomes(settings=settings, hub=self.hub, writer=self._writer,
                                 live=sessions.find)
        sessions.on_forget = self.outcomes.forget
        self.following = MapFollowing(sessions, control=self.control)
        self._idle = asyncio.Event()
        self._closing = False
        self.budget = FrameBudget(max_bytes=settings.max_queued_bytes,
                                  max_frames=settings.max_queued_frames,
                                  accepted=self._accepted_held)

    # -- life cycle -------------------------------------------------------------------------

    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        self.loop = self.outcomes.loop = self.sessions.loop = self.following.loop = loop
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
        return sum(len(live.arrivals) for live in self.sessions.held())

    def _accepted_held(self) -> dict[str, Held]:
        """The frames accepted and not answered, by session (for :attr:`budget`)."""
        return {live.id: Held(len(live.arrivals), sum(a.size for a in live.arrivals.values()))
                for live in self.sessions.held() if live.arrivals}

    async def settle_gone(self) -> int:
        """Shared engine: report the frames that API processes no longer alive left queued
        (failed, kind ``interrupted``, published to their sessions' streams); how many."""
        alive = await asyncio.to_thread(self.engine.live_instances, GONE_AFTER_S)
        if alive is None:
            return 0
        frames = await asyncio.to_thread(self._settle_gone, alive | {self.sessions.owner})
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

    # -- frames (event loop) ----------------------------------------------------------------

    async def accept(self, live: LiveSession, data: bytes, *, seq: int | None,
                     captured_at: datetime | None, t0: float,
                     metadata: FrameMetadata | None = None,
                     header: ImageHeader | None = None,
                     admitted: bool = False) -> tuple[int, asyncio.Future]:
        """Number a frame whose bytes passed the header checks and queue its record.

        Returns the frame's seq and a future that resolves (with the seq) once the frame is
        recorded and queued in the engine, or fails with a 503 :class:`Problem` when it
        could not be recorded (nothing was done with it then).

        A local engine's frames are numbered here, with no await between the sequence
        check and the queueing; a shared engine numbers them itself, across API processes.

        ``admitted``: the frame's body was let in by :attr:`budget` already. ``header``: what
        :func:`app.imagecheck.check_image` read of it (the worker does not read it again).

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
        if live.moving is not None or self.following.behind(live) is not None:
            # the map has a new revision: this frame and the next run on it
            await self.following.follow(live)
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
                          live.last_seq, metadata, len(data),
                          None if header is None else header.core)
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
                await self.sessions.reopen(live)
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
        await self.sessions.reopen(live)
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
                                     metadata=arrival.metadata,
                                     header=arrival.header)
        except (KeyError, EngineClosed, WorkerDied) as exc:
            if isinstance(exc, KeyError):
                self.sessions.release_for_reload(live)
            kind = "worker_died" if isinstance(exc, WorkerDied) else "not_open"
            self.outcomes.on_outcome(FrameFailed(
                live.id, seq, kind, f"the engine could not take the frame: {exc}"))
        _resolve(arrival.queued, seq)

    # -- outcomes ---------------------------------------------------------------------------

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


def _resolve(fut: asyncio.Future, value=None, *, exception: BaseException | None = None) -> None:
    """Settle a future nobody may be waiting on any more (its request was cancelled)."""
    if fut.done():
        return
    if exception is not None:
        fut.set_exception(exception)
        fut.exception()  # retrieved: a WebSocket frame's refusal is reported elsewhere
    else:
        fut.set_result(value)
