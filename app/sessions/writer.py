"""The frame intake's writer thread: stores what the intake queues, in order and in
batches, and hands each batch back to the event loop to settle.

Items: :class:`Accepted` (a frame's record, stored before the frame goes to a worker),
:class:`~app.sessions.store.OutcomeRecord` (a frame's outcome or a checkpoint) and
:class:`Barrier` (stores nothing; settles after everything queued before it).
"""

from __future__ import annotations

import asyncio
import logging
import queue
import threading
from collections.abc import Callable
from dataclasses import dataclass

from vloc.app.engine import FrameDone, FrameFailed
from vloc.app.metrics import Metrics
from vloc.app.sessions.schemas import FrameError
from vloc.app.sessions.store import FrameRecord, FrameStore, OutcomeRecord
from vloc.app.stream.hub import Encoded

log = logging.getLogger(__name__)

BATCH = 512
_STOP = object()

Settled = list[tuple[object, Exception | None]]
"""Each item of a batch with the error that refused it (None when stored)."""


@dataclass(frozen=True, slots=True)
class Accepted:
    """A frame's record, with the live session that accepted it."""

    live: object
    record: FrameRecord


@dataclass(frozen=True, slots=True)
class Barrier:
    """Settles once every item queued before it has been settled."""

    done: asyncio.Future


class Writer:
    """One thread writing through a :class:`FrameStore`; ``settle(items)`` runs on the
    loop after each batch.

    An outcome the database refuses is replaced by a ``not_stored`` failure, stored too
    where possible, and settled with its error so that the loop publishes it.
    """

    def __init__(self, store: FrameStore, metrics: Metrics,
                 settle: Callable[[Settled], None]) -> None:
        self.store = store
        self.metrics = metrics
        self.settle = settle
        self.loop: asyncio.AbstractEventLoop | None = None
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._thread: threading.Thread | None = None

    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        self.loop = loop
        self._thread = threading.Thread(target=self._run, name="frame-writer", daemon=True)
        self._thread.start()

    def put(self, item: Accepted | OutcomeRecord | Barrier) -> None:
        """Queue an item; callable from any thread."""
        self._queue.put(item)

    def stop(self, timeout: float) -> None:
        """Write what is queued, then end the thread."""
        if self._thread is not None:
            self._queue.put(_STOP)
            self._thread.join(timeout)

    def _run(self) -> None:
        while True:
            batch, stop = self._take()
            if batch:
                try:
                    done = self._write(batch)
                except Exception as exc:  # noqa: BLE001 - the thread must go on
                    log.exception("writing a batch of %d items failed", len(batch))
                    # Nobody waits for ever: records refused, outcomes and barriers settled.
                    done = [(item, exc if isinstance(item, Accepted) else None)
                            for item in batch]
                if self.loop is not None and not self.loop.is_closed():
                    self.loop.call_soon_threadsafe(self.settle, done)
            if stop:
                return

    def _take(self) -> tuple[list, bool]:
        first = self._queue.get()
        if first is _STOP:
            return [], True
        batch = [first]
        while len(batch) < BATCH:
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                break
            if item is _STOP:
                return batch, True
            batch.append(item)
        return batch, False

    def _write(self, batch: list) -> Settled:
        rows = [(i, item.record if isinstance(item, Accepted) else item)
                for i, item in enumerate(batch) if not isinstance(item, Barrier)]
        refused = self.store.write([row for _, row in rows])
        errors = {rows[j][0]: exc for j, exc in refused.items()}
        done: Settled = []
        for i, item in enumerate(batch):
            error = errors.get(i)
            if isinstance(item, OutcomeRecord):
                if error is None:
                    self._count(item.message)
                elif item.message is None:
                    log.error("a checkpoint of session %s could not be stored: %r",
                              item.outcome.session_id, error)
                else:
                    item = self._not_stored(item, error)
            elif isinstance(item, Accepted) and error is not None:
                log.error("frame %d of session %s could not be recorded: %r",
                          item.record.seq, item.record.session_id, error)
            done.append((item, error))
        return done

    def _not_stored(self, item: OutcomeRecord, error: Exception) -> OutcomeRecord:
        o, msg = item.outcome, item.message
        log.error("the outcome of frame %d of session %s could not be stored: %r",
                  o.seq, o.session_id, error)
        what = "estimate" if isinstance(o, FrameDone) else "failure"
        # The driver's message may quote the statement and its values: the type is enough.
        failed = FrameFailed(o.session_id, o.seq, "not_stored",
                             f"the frame's {what} could not be stored "
                             f"({type(error).__name__})")
        message = FrameError(session_id=o.session_id, seq=o.seq,
                             captured_at=msg["captured_at"], kind=failed.kind,
                             reason=failed.reason, latency_ms=msg["latency_ms"])
        replacement = OutcomeRecord(failed, Encoded.of(message))
        if self.store.write([replacement]):
            log.error("frame %d of session %s: its failure could not be stored either",
                      o.seq, o.session_id)
        self._count(replacement.message)
        return replacement

    def _count(self, m: Encoded | None) -> None:
        if m is None:
            return
        if m["type"] == "pose":
            self.metrics.frames_processed.labels(m["feature"]).inc()
            self.metrics.step_seconds.labels(m["feature"]).observe(m["processing_ms"] / 1e3)
            self.metrics.frame_latency.observe(m["latency_ms"] / 1e3)
        else:
            self.metrics.frames_failed.labels(m["kind"]).inc()
