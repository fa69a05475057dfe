"""What becomes of a frame's outcome: its message, published at once, stored, then settled.

The engine's reader thread hands each outcome to :meth:`Outcomes.on_outcome`, which turns it
into its message (:mod:`app.sessions.pose` for an estimate, a ``frame_error`` otherwise),
written as JSON once (:class:`~app.stream.hub.Encoded`: the socket, Redis and a waiting
request send that text), has the event loop publish the stream's copy at once and queues the
message with its row for the writer: the stream never waits for the database. Once the
writer has stored it (or the database refused it: the stream then also hears a
``frame_error`` of kind ``not_stored``),
:meth:`Outcomes.settle` wakes the ``?wait=true`` request waiting on it and the frame leaves
its session's arrivals.
"""

from __future__ import annotations

import asyncio
import math
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from typing import TYPE_CHECKING

from vloc.app.config import Settings
from vloc.app.db import utcnow
from vloc.app.engine import Checkpoint, FrameDone, Outcome
from vloc.app.sessions import pose
from vloc.app.sessions.live import LiveSession
from vloc.app.sessions.schemas import FrameError, PoseEstimate
from vloc.app.sessions.store import OutcomeRecord
from vloc.app.stream.hub import Encoded, LocalHub

if TYPE_CHECKING:
    from vloc.app.sessions.writer import Writer

class Outcomes:
    """Publishing and settling the outcomes of one API process's frames.

    Parameters
    ----------
    settings : Settings
    hub : LocalHub
        Where messages are published.
    writer : Writer
        Stores the messages, then calls back :meth:`settle` on the loop.
    live : callable
        The live session of an id, or None (deleted, or not held by this process).
    """

    def __init__(self, *, settings: Settings, hub: LocalHub, writer: Writer,
                 live: Callable[[str], LiveSession | None]) -> None:
        self.settings = settings
        self.hub = hub
        self.writer = writer
        self.live = live
        self.loop: asyncio.AbstractEventLoop | None = None
        self._waiters: dict[tuple[str, int], asyncio.Future] = {}
        self._checkpoint_lock = threading.Lock()
        self._checkpoint_at: dict[str, float] = {}
        self._deferred: dict[str, Checkpoint] = {}

    def waiter(self, session_id: str, seq: int) -> asyncio.Future:
        """A future for the frame's stored message (pose or frame_error)."""
        fut = self.loop.create_future()
        self._waiters[(session_id, seq)] = fut
        return fut

    def drop_waiter(self, session_id: str, seq: int) -> None:
        self._waiters.pop((session_id, seq), None)

    def on_outcome(self, outcome: Outcome) -> None:
        """Engine reader thread: publish the message now, store it later."""
        made = self.message(outcome, time.perf_counter())
        outcome = self._checkpoint_rate(outcome)
        if made is None:
            self.writer.put(OutcomeRecord(outcome, None))
            return
        msg = Encoded.of(made[0])
        if self.loop is not None and not self.loop.is_closed():
            self.loop.call_soon_threadsafe(self.hub.publish, outcome.session_id,
                                           msg if outcome.prev_seq is None
                                           else msg.after(outcome.prev_seq))
        self.writer.put(OutcomeRecord(outcome, msg, made[1]))

    def _checkpoint_rate(self, outcome: Outcome) -> Outcome:
        """The outcome, without its state when the session's last one was stored less
        than ``VLOC_CHECKPOINT_INTERVAL_S`` ago: that state is kept here instead, the
        latest of each session, until :meth:`flush_checkpoints` (a filter state is tens of
        kilobytes; stored for every frame it was most of what the database wrote)."""
        if not isinstance(outcome, FrameDone) or outcome.state is None:
            return outcome
        now, sid = time.monotonic(), outcome.session_id
        with self._checkpoint_lock:
            if now - self._checkpoint_at.get(sid, -math.inf) >= \
                    self.settings.checkpoint_interval_s:
                self._checkpoint_at[sid] = now
                self._deferred.pop(sid, None)
                return outcome
            last = self._deferred.get(sid)
            if last is None or outcome.seq >= last.seq:
                self._deferred[sid] = Checkpoint(sid, outcome.state, outcome.seq)
        return replace(outcome, state=None)

    def flush_checkpoints(self) -> int:
        """Queue the states put off for storing (a graceful stop); how many."""
        with self._checkpoint_lock:
            deferred, self._deferred = list(self._deferred.values()), {}
        for checkpoint in deferred:
            self.writer.put(OutcomeRecord(checkpoint, None))
        return len(deferred)

    def forget(self, session_id: str) -> None:
        with self._checkpoint_lock:
            self._deferred.pop(session_id, None)
            self._checkpoint_at.pop(session_id, None)

    def message(self, outcome: Outcome, t_back: float
                ) -> tuple[PoseEstimate | FrameError, dict | None] | None:
        """The message of an outcome and, for a pose, its row; None for a checkpoint, or an
        estimate of a session deleted meanwhile: nothing to tell or keep."""
        if isinstance(outcome, Checkpoint):
            return None
        live = self.live(outcome.session_id)
        arrival = live.arrivals.get(outcome.seq) if live is not None else None
        latency_ms = (t_back - arrival.t0) * 1e3 if arrival is not None else 0.0
        captured = arrival.captured_at if arrival is not None else None
        if isinstance(outcome, FrameDone):
            if live is None:
                return None
            spec = live.spec
            # the revision the worker stepped on: a session following its map may have
            # moved since (or, on a shared engine, another process moved it)
            revision = outcome.revision if outcome.revision is not None else spec.revision
            folder = spec.map_folder if revision == spec.revision else str(
                self.settings.packed_map_dir(spec.map_id, revision))
            ctx = pose.FrameContext(
                session_id=outcome.session_id, seq=outcome.seq, map_id=spec.map_id,
                map_revision=revision, map_folder=folder, captured_at=captured,
                received_at=arrival.received_at if arrival is not None else utcnow(),
                metadata=arrival.metadata if arrival is not None else None,
                decode_ms=outcome.decode_ms, latency_ms=latency_ms)
            made = pose.from_estimate(outcome.estimate, ctx,
                                      bound_m=self.settings.converged_accuracy_m,
                                      converged_before=live.converged)
            if made[0].converged:
                live.converged = True
            return made
        return FrameError(session_id=outcome.session_id, seq=outcome.seq,
                          captured_at=captured, kind=outcome.kind, reason=outcome.reason,
                          latency_ms=latency_ms), None

    def settle(self, record: OutcomeRecord, error: Exception | None) -> None:
        """Event loop: the writer stored the outcome (or the database refused it)."""
        if record.message is None:
            return
        session_id, seq = record.outcome.session_id, record.outcome.seq
        if error is not None:
            self.hub.publish(session_id, record.message)  # the not_stored report
        live = self.live(session_id)
        if live is not None:
            live.arrivals.pop(seq, None)
        fut = self._waiters.pop((session_id, seq), None)
        if fut is not None and not fut.done():
            fut.set_result(record.message)

