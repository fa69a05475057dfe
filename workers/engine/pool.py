"""The local engine: a pool of worker processes with per-worker queues and result pipes.

Why one result pipe per worker rather than one shared queue: a process killed while writing
to a shared queue can leave half a message in it and corrupt it for everyone; a private pipe
dies with its worker, and whatever whole messages it still holds are read before the
worker's in-flight frames are reported as failed.

Threads: callers submit from any thread (the event loop, request threads); one reader
thread waits on every result pipe and every process sentinel, dispatches outcomes, and
replaces dead workers.

Workers die with the API process: each holds the read end of a lifeline pipe whose write end
only this process has, and exits when it reports end-of-file (see
:func:`~workers.engine.worker.worker_main`). Each also stamps a heartbeat in shared memory,
so that a worker that exists but does not run (stopped, starved) shows in :meth:`alive`.
"""

from __future__ import annotations

import itertools
import logging
import multiprocessing as mp
import os
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, InvalidStateError
from multiprocessing.connection import wait

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
    Ready,
    SessionSpec,
    Stop,
)
from .slots import EngineClosed, Slot, WorkerDied, remote_error
from .worker import HEARTBEAT_S, THREAD_ENV, worker_main

log = logging.getLogger(__name__)

RESPAWN_RETRY_S = 1.0
"""How soon a worker that could not be replaced is tried again."""

STALL_S = 5.0
"""A worker whose heartbeat is older than this is not counted as alive."""

PRELOAD = ["vloc.workers.engine.worker", "vloc.workers.core.localisers",
           "vloc.workers.core.mapbuild"]


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
    """

    def __init__(self, n_workers: int, *, on_outcome: Callable[[Outcome], None] | None = None,
                 checkpoint_every: int = 1, max_pixels: int = 50_000_000,
                 start_method: str | None = None, stall_s: float = STALL_S) -> None:
        if n_workers < 1:
            raise ValueError("n_workers must be at least 1")
        if stall_s <= HEARTBEAT_S:
            raise ValueError(f"stall_s must be longer than the heartbeat ({HEARTBEAT_S} s)")
        if start_method is None:
            start_method = "forkserver" if "forkserver" in mp.get_all_start_methods() else "spawn"
        if start_method == "fork":
            raise ValueError("the fork start method is unsafe with threads; use forkserver")
        self.shared = False
        self.n_workers = n_workers
        self.on_outcome = on_outcome
        self.checkpoint_every = checkpoint_every
        self.max_pixels = max_pixels
        self.stall_s = stall_s
        self.restarts = 0
        self._ctx = mp.get_context(start_method)
        if start_method == "forkserver":
            self._ctx.set_forkserver_preload(PRELOAD)
        self._lock = threading.RLock()
        self._slots: list[Slot] = []
        self._specs: dict[str, SessionSpec] = {}
        self._moves: dict[int, SessionSpec] = {}
        """Sessions' specs on the revision a ``move`` control (by call id) takes them to:
        theirs once it is done, so that a worker replacing theirs reopens them there."""
        self._pinned: dict[str, int] = {}
        self._states: dict[str, bytes] = {}
        self._counts: dict[str, int] = {}
        self._call_ids = itertools.count(1)
        self._running = False
        self._reader: threading.Thread | None = None
        self._wakeup_r, self._wakeup_w = self._ctx.Pipe(duplex=False)
        self._lifeline_r, self._lifeline_w = None, None

    # -- life cycle -------------------------------------------------------------------------

    def start(self, timeout: float = 120.0) -> None:
        """Start the workers and wait until each has loaded the core library."""
        for var in THREAD_ENV:
            # Inherited by the workers; the API process itself runs no numerics.
            os.environ.setdefault(var, "1")
        # The write end never leaves this process (descriptors are not inheritable and only
        # the read end is handed to the workers), so it closes exactly when we end.
        self._lifeline_r, self._lifeline_w = self._ctx.Pipe(duplex=False)
        with self._lock:
            self._slots = [self._spawn(i) for i in range(self.n_workers)]
            self._running = True
        self._reader = threading.Thread(target=self._read_loop, name="engine-reader",
                                        daemon=True)
        self._reader.start()
        for slot in list(self._slots):
            if not slot.ready.wait(timeout):
                self.close()
                raise RuntimeError(f"worker {slot.index} did not start in {timeout:g} s")

    def close(self, timeout: float = 10.0) -> None:
        """Stop the workers after the tasks already queued; fail what is left."""
        with self._lock:
            if not self._running:
                return
            self._running = False
            # A broken slot's worker is dead and its queue already closed.
            slots = [s for s in self._slots if not s.broken]
        for slot in slots:
            slot.tasks.put(Stop())
        for slot in slots:
            slot.process.join(timeout)
            if slot.process.is_alive():
                slot.process.kill()
                slot.process.join(1.0)
        self._wakeup_w.send(None)
        if self._reader is not None:
            self._reader.join(timeout)
        for slot in slots:
            self._drain(slot)
            self._fail_slot(slot, "the engine stopped")
            slot.tasks.cancel_join_thread()
            slot.tasks.close()
            slot.conn.close()
        # Whatever worker is still there (a replacement started during the stop) goes now.
        self._lifeline_w.close()
        self._lifeline_r.close()
        with self._lock:
            # Dropping the queues releases their semaphores now rather than at exit, which
            # a server stopped by a signal never reaches.
            self._slots = []

    @property
    def running(self) -> bool:
        return self._running

    def worker_pids(self) -> list[int]:
        with self._lock:
            return [slot.process.pid for slot in self._slots]

    def alive_count(self) -> int:
        """Worker processes running now."""
        with self._lock:
            if not self._running:
                return 0
            return sum(1 for s in self._slots if not s.broken and s.process.is_alive())

    def alive(self) -> bool:
        """Every worker process exists and has stamped its heartbeat within ``stall_s``."""
        now = time.monotonic()
        with self._lock:
            return self._running and all(
                not s.broken and s.process.is_alive() and now - s.heartbeat.value < self.stall_s
                for s in self._slots)

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
                     captured_at: float | None = None, metadata: dict | None = None) -> None:
        """Queue a frame; its outcome comes back through ``on_outcome``.

        ``metadata`` is :meth:`workers.core.metadata.FrameMetadata.to_dict` of the frame's
        sensor reports, already validated.

        Raises KeyError when the session is not open, ``EngineClosed`` when stopped.
        """
        with self._lock:
            self._check_running()
            slot = self._usable(self._slots[self._pinned[session_id]])
            n = self._counts[session_id] = self._counts[session_id] + 1
            slot.frames[(session_id, seq)] = None
            slot.tasks.put(FrameTask(session_id, seq, data, captured_at,
                                     checkpoint=n % self.checkpoint_every == 0,
                                     metadata=metadata))

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
            if index is not None and self._running and not self._slots[index].broken:
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
        if not self._running:
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

    def _spawn(self, index: int) -> Slot:
        tasks = self._ctx.Queue()
        reader, writer = self._ctx.Pipe(duplex=False)
        # Counted from the start, so that a worker still importing is not taken for stalled.
        heartbeat = self._ctx.RawValue("d", time.monotonic())
        process = self._ctx.Process(
            target=worker_main, name=f"vloc-worker-{index}", daemon=True,
            args=(index, tasks, writer, self.max_pixels, self._lifeline_r, heartbeat))
        process.start()
        # Our copy of the write end must go, or the pipe never reports EOF when the worker dies.
        writer.close()
        return Slot(index, process, tasks, reader, heartbeat)

    def _read_loop(self) -> None:
        while True:
            with self._lock:
                if not self._running:
                    return
                live = [s for s in self._slots if not s.broken]
                broken = [s for s in self._slots if s.broken]
            by_conn = {s.conn: s for s in live}
            by_sentinel = {s.process.sentinel: s for s in live}
            ready = wait([*by_conn, *by_sentinel, self._wakeup_r],
                         timeout=RESPAWN_RETRY_S if broken else None)
            dead: list[Slot] = []
            for obj in ready:
                if obj is self._wakeup_r:
                    continue
                slot = by_conn.get(obj) or by_sentinel.get(obj)
                if slot in dead:
                    continue
                if obj in by_conn:
                    try:
                        msg = obj.recv()
                    except (EOFError, OSError):
                        dead.append(slot)
                        continue
                    self._dispatch(slot, msg)
                elif not slot.process.is_alive():
                    dead.append(slot)
            for slot in dead:
                self._replace(slot)
            for slot in broken:
                self._revive(slot)

    def _dispatch(self, slot: Slot, msg) -> None:
        if isinstance(msg, Ready):
            slot.ready.set()
            return
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

    def _drain(self, slot: Slot) -> None:
        """Dispatch the whole messages a (dead or stopped) worker left in its pipe."""
        try:
            while slot.conn.poll():
                self._dispatch(slot, slot.conn.recv())
        except (EOFError, OSError, ValueError):
            pass  # the rest is a message the worker did not finish writing

    def _fail_slot(self, slot: Slot, reason: str) -> None:
        with self._lock:
            frames, slot.frames = list(slot.frames), {}
            calls, slot.calls = slot.calls, {}
            for call_id in calls:
                self._moves.pop(call_id, None)  # never done: the session stays where it was
        for fut in calls.values():
            _settle(fut, error=WorkerDied(reason))
        for session_id, seq in frames:
            self._emit(FrameFailed(session_id, seq, "worker_died", reason))

    def _replace(self, slot: Slot) -> None:
        """A worker died: report what it held, then start another in its place."""
        self._drain(slot)
        slot.process.join(1.0)
        code = slot.process.exitcode
        reason = f"worker process {slot.process.pid} exited (code {code}) before finishing it"
        with self._lock:
            if not self._running:
                return
            # From here on nothing is queued on the dead worker: submissions get WorkerDied
            # until the replacement exists, and its in-flight work is failed below.
            slot.broken = True
        log.error("engine: worker %d (pid %s) died with code %s; replacing it",
                  slot.index, slot.process.pid, code)
        slot.tasks.cancel_join_thread()
        slot.tasks.close()
        slot.conn.close()
        self._revive(slot)
        # Reported after the replacement exists, so that whoever hears of the loss can
        # already send the session its next frame.
        self._fail_slot(slot, reason)

    def _revive(self, slot: Slot) -> None:
        """Start a worker in a dead worker's place and reopen its sessions from their last
        checkpoints, before anything else reaches the new worker."""
        with self._lock:
            if not self._running:
                return
            try:
                fresh = self._spawn(slot.index)
            except Exception as exc:  # noqa: BLE001 - retried by the reader loop
                log.error("engine: cannot start a worker in slot %d yet (%s); retrying",
                          slot.index, exc)
                return
            fresh.sessions = set(slot.sessions)
            for session_id in sorted(fresh.sessions):
                fresh.tasks.put(OpenSession(self._specs[session_id],
                                            self._states.get(session_id)))
            self._slots[slot.index] = fresh
            self.restarts += 1


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
