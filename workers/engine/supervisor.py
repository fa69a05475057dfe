"""The local engine's worker processes: started, watched, and replaced when one dies.

Why one result pipe per worker rather than one shared queue: a process killed while writing
to a shared queue can leave half a message in it and corrupt it for everyone; a private pipe
dies with its worker, and whatever whole messages it still holds are read before the
worker's in-flight work is reported as lost.

Threads: one reader thread waits on every result pipe and every process sentinel, hands
each message to the engine (:attr:`WorkerSupervisor.on_message`), and replaces dead
workers.

Workers die with the API process: each holds the read end of a lifeline pipe whose write end
only this process has, and exits when it reports end-of-file (see
:func:`~workers.engine.worker.worker_main`). Each also stamps a heartbeat in shared memory,
so that a worker that exists but does not run (stopped, starved) shows in :meth:`alive`.

What a worker runs, and which worker runs what, is the engine's
(:class:`~workers.engine.pool.LocalEngine`): the supervisor knows slots, not sessions.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import threading
import time
from collections.abc import Callable, Sequence
from multiprocessing.connection import wait

from .messages import OpenSession, Ready, Stop
from .slots import Slot
from .worker import HEARTBEAT_S, worker_main

log = logging.getLogger(__name__)

RESPAWN_RETRY_S = 1.0
"""How soon a worker that could not be replaced is tried again."""

STALL_S = 5.0
"""A worker whose heartbeat is older than this is not counted as alive."""

PRELOAD = ["vloc.workers.engine.worker", "vloc.workers.core.localisers",
           "vloc.workers.core.mapbuild", "pycolmap"]
"""What the forkserver imports once, so that every worker forked from it starts with it:
the core library, and COLMAP, which the core imports where a map's geometry needs it (0.2 s
of a worker's first build otherwise)."""


class WorkerSupervisor:
    """``n_workers`` worker processes, each in its :class:`Slot`.

    Parameters
    ----------
    n_workers : int
    lock : threading.RLock
        The engine's lock: it guards the slots and what the engine keeps beside them.
    on_message : callable(Slot, message)
        Reader thread: a message from a worker (anything but its ``Ready``).
    on_lost : callable(Slot, reason)
        Reader thread, or :meth:`close`: the slot's worker is gone with the frames and
        calls it held (they are still in the slot).
    reopen : callable(session ids) -> list of OpenSession
        The tasks that reopen the sessions of a dead worker in its replacement, from their
        last checkpoints.
    start_method, max_pixels, stall_s, preload
        As :class:`~workers.engine.pool.LocalEngine`'s.
    """

    def __init__(self, n_workers: int, *, lock: threading.RLock,
                 on_message: Callable[[Slot, object], None],
                 on_lost: Callable[[Slot, str], None],
                 reopen: Callable[[list[str]], list[OpenSession]],
                 start_method: str, max_pixels: int, stall_s: float = STALL_S,
                 preload: Sequence[str] = ()) -> None:
        if n_workers < 1:
            raise ValueError("n_workers must be at least 1")
        if stall_s <= HEARTBEAT_S:
            raise ValueError(f"stall_s must be longer than the heartbeat ({HEARTBEAT_S} s)")
        self.n_workers = n_workers
        self.on_message = on_message
        self.on_lost = on_lost
        self.reopen = reopen
        self.max_pixels = max_pixels
        self.stall_s = stall_s
        self.restarts = 0
        self.slots: list[Slot] = []
        self.running = False
        self._lock = lock
        self._ctx = mp.get_context(start_method)
        self.preload = [*PRELOAD, *preload]
        if start_method == "forkserver":
            self._ctx.set_forkserver_preload(self.preload)
        self._reader: threading.Thread | None = None
        self._wakeup_r, self._wakeup_w = self._ctx.Pipe(duplex=False)
        self._lifeline_r, self._lifeline_w = None, None

    def start(self, timeout: float) -> None:
        """Start the workers and wait until each has loaded the core library."""
        # The write end never leaves this process (descriptors are not inheritable and only
        # the read end is handed to the workers), so it closes exactly when we end.
        self._lifeline_r, self._lifeline_w = self._ctx.Pipe(duplex=False)
        with self._lock:
            self.slots = [self._spawn(i) for i in range(self.n_workers)]
            self.running = True
        self._reader = threading.Thread(target=self._read_loop, name="engine-reader",
                                        daemon=True)
        self._reader.start()
        for slot in list(self.slots):
            if not slot.ready.wait(timeout):
                self.close()
                raise RuntimeError(f"worker {slot.index} did not start in {timeout:g} s")

    def close(self, timeout: float = 10.0) -> None:
        """Stop the workers after the tasks already queued; what is left is lost."""
        with self._lock:
            if not self.running:
                return
            self.running = False
            # A broken slot's worker is dead and its queue already closed.
            slots = [s for s in self.slots if not s.broken]
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
            self.on_lost(slot, "the engine stopped")
            slot.tasks.cancel_join_thread()
            slot.tasks.close()
            slot.conn.close()
        # Whatever worker is still there (a replacement started during the stop) goes now.
        self._lifeline_w.close()
        self._lifeline_r.close()
        with self._lock:
            # Dropping the queues releases their semaphores now rather than at exit, which
            # a server stopped by a signal never reaches.
            self.slots = []

    def worker_pids(self) -> list[int]:
        with self._lock:
            return [slot.process.pid for slot in self.slots]

    def alive_count(self) -> int:
        """Worker processes running now."""
        with self._lock:
            if not self.running:
                return 0
            return sum(1 for s in self.slots if not s.broken and s.process.is_alive())

    def alive(self) -> bool:
        """Every worker process exists and has stamped its heartbeat within ``stall_s``."""
        now = time.monotonic()
        with self._lock:
            return self.running and all(
                not s.broken and s.process.is_alive() and now - s.heartbeat.value < self.stall_s
                for s in self.slots)

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
                if not self.running:
                    return
                live = [s for s in self.slots if not s.broken]
                broken = [s for s in self.slots if s.broken]
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
        else:
            self.on_message(slot, msg)

    def _drain(self, slot: Slot) -> None:
        """Dispatch the whole messages a (dead or stopped) worker left in its pipe."""
        try:
            while slot.conn.poll():
                self._dispatch(slot, slot.conn.recv())
        except (EOFError, OSError, ValueError):
            pass  # the rest is a message the worker did not finish writing

    def _replace(self, slot: Slot) -> None:
        """A worker died: report what it held, then start another in its place."""
        self._drain(slot)
        slot.process.join(1.0)
        code = slot.process.exitcode
        reason = f"worker process {slot.process.pid} exited (code {code}) before finishing it"
        with self._lock:
            if not self.running:
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
        self.on_lost(slot, reason)

    def _revive(self, slot: Slot) -> None:
        """Start a worker in a dead worker's place and reopen its sessions, before anything
        else reaches the new worker."""
        with self._lock:
            if not self.running:
                return
            try:
                fresh = self._spawn(slot.index)
            except Exception as exc:  # noqa: BLE001 - retried by the reader loop
                log.error("engine: cannot start a worker in slot %d yet (%s); retrying",
                          slot.index, exc)
                return
            fresh.sessions = set(slot.sessions)
            for task in self.reopen(sorted(fresh.sessions)):
                fresh.tasks.put(task)
            self.slots[slot.index] = fresh
            self.restarts += 1
