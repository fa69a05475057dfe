"""The local engine: sessions and calls routed to a pool of worker processes.

Each session is pinned to one worker (the least busy when it opens) and its frames and
controls go to that worker's queue in order; a call goes to the least busy worker. The
processes themselves (started, watched, replaced when one dies) are
:class:`~workers.engine.supervisor.WorkerSupervisor`'s; when it replaces a worker, the
sessions that worker held reopen in the new one from their last checkpoints, and the frames
and calls it held are reported failed.

Threads: callers submit from any thread (the event loop, request threads); the
supervisor's reader thread hands every worker message to :meth:`LocalEngine._on_message`,
which settles calls and passes frame outcomes on to ``on_outcome``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from vloc.workers.core.image import Header
    from vloc.workers.core.metadata import FrameMetadata

import itertools
import logging
import multiprocessing as mp
import os
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import Future, InvalidStateError

from .messages import (
    CallDone,
    CallTask,
    Checkpoint,
    CloseSession,
    ControlTask,
    FrameDone,
    FrameFailed,
    FrameTask,
    OpenSession,
    Outcome,
    SessionSpec,
)
from .slots import EngineClosed, Slot, WorkerDied, remote_error
from .supervisor import STALL_S, WorkerSupervisor
from .worker import THREAD_ENV

log = logging.getLogger(__name__)


class LocalEngine:
    """A pool of worker processes running sessions and calls.

    Parameters
    ----------
    n_workers : int
    on_outcome : callable(FrameDone | FrameFailed | Checkpoint) or None
        Called in the engine's reader thread for every frame outcome and for the state a
        control leaves behind, in each session's order; keep it short (hand the outcome to
        another thread).
    checkpoint_every : int
        Ask for the localiser's state after every ``checkpoint_every``-th frame of a session.
    max_pixels : int
        Decompression-bomb guard for frame decoding in the workers.
    start_method : str or None
        ``"forkserver"`` (default where available) or ``"spawn"``; never ``"fork"``, which
        copies the parent's threads' locks in whatever state they are in.
    stall_s : float
        A worker whose heartbeat (stamped every ``HEARTBEAT_S`` while it can run) is older
        than this does not count as alive.
    preload : sequence of str
        Modules the workers should start with, besides the core library: those of the
        tasks the caller will run (:meth:`call`). Under ``forkserver`` they are imported
        once, in the server the workers are forked from, by the first engine of the
        process to start one (Python keeps one forkserver a process).
    """

    def __init__(self, n_workers: int, *, on_outcome: Callable[[Outcome], None] | None = None,
                 checkpoint_every: int = 1, max_pixels: int = 50_000_000,
                 start_method: str | None = None, stall_s: float = STALL_S,
                 preload: Sequence[str] = ()) -> None:
        if start_method is None:
            start_method = "forkserver" if "forkserver" in mp.get_all_start_methods() else "spawn"
        if start_method == "fork":
            raise ValueError("the fork start method is unsafe with threads; use forkserver")
        self.shared = False
        self.on_outcome = on_outcome
        self.checkpoint_every = checkpoint_every
        self._lock = threading.RLock()
        self.supervisor = WorkerSupervisor(
            n_workers, lock=self._lock, on_message=self._on_message, on_lost=self._on_lost,
            reopen=self._reopen_tasks, start_method=start_method, max_pixels=max_pixels,
            stall_s=stall_s, preload=preload)
        self._specs: dict[str, SessionSpec] = {}
        self._moves: dict[int, SessionSpec] = {}
        """Sessions' specs on the revision a ``move`` control (by call id) takes them to:
        theirs once it is done, so that a worker replacing theirs reopens them there."""
        self._pinned: dict[str, int] = {}
        self._states: dict[str, bytes] = {}
        self._counts: dict[str, int] = {}
        self._call_ids = itertools.count(1)

    # -- life cycle -------------------------------------------------------------------------

    def start(self, timeout: float = 120.0) -> None:
        """Start the workers and wait until each has loaded the core library."""
        for var in THREAD_ENV:
            # Inherited by the workers; the API process itself runs no numerics.
            os.environ.setdefault(var, "1")
        self.supervisor.start(timeout)

    def close(self, timeout: float = 10.0) -> None:
        """Stop the workers after the tasks already queued; fail what is left."""
        self.supervisor.close(timeout)

    @property
    def running(self) -> bool:
        return self.supervisor.running

    @property
    def n_workers(self) -> int:
        return self.supervisor.n_workers

    @property
    def restarts(self) -> int:
        """Workers replaced since the start."""
        return self.supervisor.restarts

    def worker_pids(self) -> list[int]:
        return self.supervisor.worker_pids()

    def alive_count(self) -> int:
        """Worker processes running now."""
        return self.supervisor.alive_count()

    def alive(self) -> bool:
        """Every worker process exists and has stamped its heartbeat within ``stall_s``."""
        return self.supervisor.alive()

    @property
    def _slots(self) -> list[Slot]:
        return self.supervisor.slots

    # -- sessions ---------------------------------------------------------------------------

    def open_session(self, spec: SessionSpec, *, state: bytes | None = None,
                     last_seq: int | None = None) -> Future:
        """Pin a session to the least busy worker and create its localiser there.

        ``state`` restores a checkpoint. ``last_seq`` is for shared engines: the API process
        numbers the frames of a local engine's sessions itself. The future resolves once the localiser exists, or
        fails with the worker's error (the session is then not open).
        """
        fut: Future = Future()
        with self._lock:
            self._check_running()
            slot = self._usable(self._slots[self._pinned[spec.session_id]]
                                if spec.session_id in self._pinned else min(
                self._slots, key=lambda s: (s.broken, len(s.sessions), s.load, s.index)))
            call_id = next(self._call_ids)
            self._specs[spec.session_id] = spec
            self._pinned[spec.session_id] = slot.index
            self._counts.setdefault(spec.session_id, 0)
            if state is not None:
                self._states[spec.session_id] = state
            slot.sessions.add(spec.session_id)
            slot.calls[call_id] = fut
            slot.tasks.put(OpenSession(spec, state, call_id))
        fut.add_done_callback(lambda f: f.exception() and self._forget(spec.session_id))
        return fut

    def is_open(self, session_id: str) -> bool:
        with self._lock:
            return session_id in self._pinned

    def worker_index(self, session_id: str) -> int:
        with self._lock:
            return self._pinned[session_id]

    def submit_frame(self, session_id: str, seq: int, data: bytes, *,
                     captured_at: float | None = None,
                     metadata: FrameMetadata | None = None,
                     header: Header | None = None) -> None:
        """Queue a frame; its outcome comes back through ``on_outcome``.

        ``metadata`` is the frame's sensor reports, already validated; ``header`` what its
        checked image header says.

        Raises KeyError when the session is not open, ``EngineClosed`` when stopped.
        """
        with self._lock:
            self._check_running()
            slot = self._usable(self._slots[self._pinned[session_id]])
            n = self._counts[session_id] = self._counts[session_id] + 1
            slot.frames[(session_id, seq)] = None
            slot.tasks.put(FrameTask(session_id, seq, data, captured_at,
                                     checkpoint=n % self.checkpoint_every == 0,
                                     metadata=metadata, header=header))

    def pending_frames(self, session_id: str) -> int:
        with self._lock:
            index = self._pinned.get(session_id)
            if index is None:
                return 0
            return sum(1 for sid, _ in self._slots[index].frames if sid == session_id)

    def control(self, session_id: str, op: str, **kwargs) -> Future:
        """``reset`` / ``set_initial_pose`` / ``stats`` / ``move``, in order with the
        session's frames."""
        fut: Future = Future()
        with self._lock:
            self._check_running()
            slot = self._usable(self._slots[self._pinned[session_id]])
            call_id = next(self._call_ids)
            if op == "move":
                self._moves[call_id] = kwargs["spec"]
            slot.calls[call_id] = fut
            slot.tasks.put(ControlTask(call_id, session_id, op, kwargs))
        return fut

    def close_session(self, session_id: str) -> None:
        with self._lock:
            index = self._pinned.get(session_id)
            self._forget(session_id)
            if index is not None and self.running and not self._slots[index].broken:
                self._slots[index].tasks.put(CloseSession(session_id))

    def last_state(self, session_id: str) -> bytes | None:
        with self._lock:
            return self._states.get(session_id)

    # -- calls ------------------------------------------------------------------------------

    def call(self, fn: Callable | str, *args, **kwargs) -> Future:
        """Run ``fn`` (a module-level function, or ``"module:function"``) on the least busy
        worker."""
        fut: Future = Future()
        with self._lock:
            self._check_running()
            slot = self._usable(min(self._slots, key=lambda s: (s.broken, s.load, s.index)))
            call_id = next(self._call_ids)
            slot.calls[call_id] = fut
            slot.tasks.put(CallTask(call_id, fn, args, kwargs))
        return fut

    # -- internals --------------------------------------------------------------------------

    def _check_running(self) -> None:
        if not self.supervisor.running:
            raise EngineClosed("the engine is not running")

    @staticmethod
    def _usable(slot: Slot) -> Slot:
        if slot.broken:
            raise WorkerDied(f"worker {slot.index} died and is being replaced; retry")
        return slot

    def _forget(self, session_id: str) -> None:
        with self._lock:
            index = self._pinned.pop(session_id, None)
            if index is not None and index < len(self._slots):
                self._slots[index].sessions.discard(session_id)
            self._specs.pop(session_id, None)
            self._states.pop(session_id, None)
            self._counts.pop(session_id, None)

    def _reopen_tasks(self, session_ids: list[str]) -> list[OpenSession]:
        """Supervisor: the tasks that reopen a dead worker's sessions in its replacement."""
        with self._lock:
            return [OpenSession(self._specs[sid], self._states.get(sid)) for sid in session_ids]

    def _on_message(self, slot: Slot, msg) -> None:
        """Supervisor's reader thread: a worker's message."""
        if isinstance(msg, FrameDone | FrameFailed):
            with self._lock:
                slot.frames.pop((msg.session_id, msg.seq), None)
                if isinstance(msg, FrameDone) and msg.state is not None \
                        and msg.session_id in self._pinned:
                    self._states[msg.session_id] = msg.state
            self._emit(msg)
            return
        if isinstance(msg, CallDone):
            with self._lock:
                fut = slot.calls.pop(msg.call_id, None)
                moved = self._moves.pop(msg.call_id, None)
                if moved is not None and msg.ok and msg.session_id in self._specs:
                    self._specs[msg.session_id] = moved
                checkpoint = msg.state is not None and msg.session_id in self._pinned
                if checkpoint:
                    self._states[msg.session_id] = msg.state
            if checkpoint:
                self._emit(Checkpoint(msg.session_id, msg.state))
            if fut is not None:
                if msg.ok:
                    _settle(fut, value=msg.value)
                else:
                    _settle(fut, error=remote_error(msg.error_type, msg.error))
            return
        log.warning("engine: unexpected message %r", type(msg).__name__)

    def _emit(self, outcome: Outcome) -> None:
        if self.on_outcome is None:
            return
        try:
            self.on_outcome(outcome)
        except Exception:  # noqa: BLE001 - a broken consumer must not kill the reader
            log.exception("engine: frame consumer failed")

    def _on_lost(self, slot: Slot, reason: str) -> None:
        """Supervisor: the slot's worker is gone; fail the frames and calls it held."""
        with self._lock:
            frames, slot.frames = list(slot.frames), {}
            calls, slot.calls = slot.calls, {}
            for call_id in calls:
                self._moves.pop(call_id, None)  # never done: the session stays where it was
        for fut in calls.values():
            _settle(fut, error=WorkerDied(reason))
        for session_id, seq in frames:
            self._emit(FrameFailed(session_id, seq, "worker_died", reason))


def _settle(fut: Future, *, value=None, error: BaseException | None = None) -> None:
    """Resolve a caller's future, unless the caller cancelled it (it stopped waiting: a
    timeout, a request that went away); the reader thread must never fail on that."""
    try:
        if error is not None:
            fut.set_exception(error)
        else:
            fut.set_result(value)
    except InvalidStateError:
        pass
