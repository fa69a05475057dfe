"""The worker process: a loop over its task queue, one localiser per session it holds.

A worker handles its tasks strictly in order, so the frames of a session (all pinned to the
same worker) are stepped in the order the API accepted them. Maps are loaded memory-mapped
once per (map id, revision) and shared by every session on the worker, and by every worker
through the page cache.
"""

from __future__ import annotations

import importlib
import inspect
import os
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from multiprocessing.connection import Connection

from .messages import (
    CallDone,
    CallTask,
    CloseSession,
    ControlTask,
    FrameDone,
    FrameFailed,
    FrameTask,
    OpenSession,
    Ready,
    SessionSpec,
    Stop,
)

HEARTBEAT_S = 0.25
"""How often a worker stamps its heartbeat and looks at its lifeline."""
EXIT_ORPHANED = 70
"""Exit status of a worker whose API process is gone."""
THREAD_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def resolve(ref: str) -> Callable:
    """``"package.module:function"`` -> the function."""
    module, _, attr = ref.partition(":")
    if not module or not attr:
        raise ValueError(f"expected 'module:function', got {ref!r}")
    return getattr(importlib.import_module(module), attr)


def _function(fn: Callable | str) -> Callable:
    return fn if callable(fn) else resolve(fn)


class WorkerState:
    """The sessions and maps one worker holds; :meth:`handle` runs one task."""

    def __init__(self, *, max_pixels: int) -> None:
        self.max_pixels = max_pixels
        self.sessions: dict[str, tuple[SessionSpec, object]] = {}
        self.maps: dict[tuple[str, int], object] = {}
        self.reported: dict[str, int] = {}
        """Each open session's last frame outcome (its seq), the next one's ``prev_seq``."""

    def handle(self, task) -> object | None:
        if isinstance(task, FrameTask):
            return self._frame(task)
        if isinstance(task, OpenSession):
            return self._guarded(task.call_id, task.spec.session_id, self._open, task)
        if isinstance(task, ControlTask):
            return self._guarded(task.call_id, task.session_id, self._control, task)
        if isinstance(task, CallTask):
            return self._guarded(task.call_id, None,
                                 lambda t: (_function(t.fn)(*t.args, **t.kwargs), None), task)
        if isinstance(task, CloseSession):
            self._close(task.session_id)
            return None
        raise TypeError(f"unknown task {type(task).__name__}")

    # -- tasks ------------------------------------------------------------------------------

    def _frame(self, task: FrameTask) -> FrameDone | FrameFailed:
        held = self.sessions.get(task.session_id)
        if held is None:
            return FrameFailed(task.session_id, task.seq, "not_open",
                               "the session is not open on its worker")
        outcome = self._step(task, held[1])
        prev = self.reported.get(task.session_id)
        self.reported[task.session_id] = task.seq
        if isinstance(outcome, FrameDone):
            outcome = replace(outcome, revision=held[0].revision)
        return replace(outcome, prev_seq=prev)

    def _step(self, task: FrameTask, localiser) -> FrameDone | FrameFailed:
        from vloc.workers.core.image import ImageError
        from vloc.workers.core.stepping import step_image

        try:
            record = step_image(localiser, task.data, max_pixels=self.max_pixels,
                                captured_at=task.captured_at, metadata=task.metadata,
                                header=task.header)
            state = localiser.get_state() if task.checkpoint else None
        except ImageError as exc:
            return FrameFailed(task.session_id, task.seq, "bad_image", str(exc))
        except Exception as exc:  # noqa: BLE001 - reported on the stream, the worker lives on
            return FrameFailed(task.session_id, task.seq, "error",
                               f"{type(exc).__name__}: {exc}")
        return FrameDone(task.session_id, task.seq, record.estimate, state, record.decode_ms)

    def _open(self, task: OpenSession) -> tuple[object, bytes | None]:
        spec = task.spec
        map_data = self._map(spec) if spec.map_folder else None
        factory = resolve(spec.factory)
        localiser = factory(spec.mode, map_data, dict(spec.params), seed=spec.seed)
        if task.state is not None:
            localiser.set_state(task.state)
        self._close(spec.session_id)
        self.sessions[spec.session_id] = (spec, localiser)
        return None, None

    def _control(self, task: ControlTask) -> tuple[object, bytes | None]:
        held = self.sessions.get(task.session_id)
        if held is None:
            raise KeyError(f"session {task.session_id} is not open on this worker")
        spec, localiser = held
        if task.op == "reset":
            localiser.reset()
        elif task.op == "set_initial_pose":
            x, y = self._local_xy(spec, task.kwargs)
            heading = {k: float(task.kwargs[k]) for k in ("heading_deg", "heading_sigma_deg")
                       if task.kwargs.get(k) is not None}
            if heading and "heading_deg" not in inspect.signature(
                    localiser.set_initial_pose).parameters:
                raise ValueError(f"the {spec.mode} localiser keeps no heading between frames; "
                                 "send the heading with each frame (heading_deg) instead")
            localiser.set_initial_pose(x, y, float(task.kwargs.get("sigma", 5.0)), **heading)
        elif task.op == "stats":
            return dict(getattr(localiser, "stats", {})), None
        elif task.op == "move":
            return self._move(spec, localiser, task.kwargs["spec"])
        else:
            raise ValueError(f"unknown control {task.op!r}")
        return None, localiser.get_state()

    def _move(self, spec: SessionSpec, localiser, to: SessionSpec) -> tuple[int, bytes]:
        """Move a session to another revision of its map between two frames: a localiser
        on the new revision takes up the old one's state (:meth:`Localiser.set_state`
        carries it into the new revision's frame). Moving to the revision it is on
        changes nothing. Returns the revision and the state."""
        if (to.session_id, to.map_id) != (spec.session_id, spec.map_id):
            raise ValueError("a session moves to another revision of its own map only")
        if to.revision == spec.revision:
            return spec.revision, localiser.get_state()
        if not getattr(localiser, "moves_between_revisions", False):
            raise ValueError(f"a session of factory {spec.factory} stays on the revision it "
                             "was created on")
        map_data = self._map(to) if to.map_folder else None
        moved = resolve(to.factory)(to.mode, map_data, dict(to.params), seed=to.seed)
        moved.set_state(localiser.get_state())
        reported = self.reported.get(spec.session_id)
        self._close(spec.session_id)
        self.sessions[to.session_id] = (to, moved)
        if reported is not None:
            self.reported[to.session_id] = reported
        return to.revision, moved.get_state()

    def _local_xy(self, spec: SessionSpec, kwargs: dict) -> tuple[float, float]:
        """x/y as given, or lat/lon converted in the frame of the session's map revision."""
        if "lat" in kwargs:
            east, north = self._map(spec).origin.to_local(kwargs["lat"], kwargs["lon"])
            return float(east), float(north)
        return float(kwargs["x"]), float(kwargs["y"])

    def _close(self, session_id: str) -> None:
        held = self.sessions.pop(session_id, None)
        self.reported.pop(session_id, None)
        if held is None:
            return
        key = (held[0].map_id, held[0].revision)
        # Drop the map when no session uses it any more: it is memory-mapped, so loading
        # it again later costs page-cache hits, not a copy.
        if all((s.map_id, s.revision) != key for s, _ in self.sessions.values()):
            self.maps.pop(key, None)

    def _map(self, spec: SessionSpec):
        key = (spec.map_id, spec.revision)
        if key not in self.maps:
            from vloc.workers.core.mapdata import open_map

            self.maps[key] = open_map(spec.map_folder)
        return self.maps[key]

    @staticmethod
    def _guarded(call_id, session_id, fn, task) -> CallDone | None:
        try:
            value, state = fn(task)
        except Exception as exc:  # noqa: BLE001 - the caller gets the error, the worker lives on
            if call_id is None:
                return None
            return CallDone(call_id, False, None, _builtin_base(exc), _describe(exc), session_id)
        if call_id is None:
            return None
        return CallDone(call_id, True, value, session_id=session_id, state=state)


def _builtin_base(exc: BaseException) -> str:
    """The nearest builtin class of an exception, which the API process can rebuild."""
    return next(c.__name__ for c in type(exc).__mro__ if c.__module__ == "builtins")


def _describe(exc: BaseException) -> str:
    name = type(exc).__name__
    return str(exc) if name == _builtin_base(exc) else f"{name}: {exc}"


def worker_main(index: int, tasks, results: Connection, max_pixels: int,
                lifeline: Connection, heartbeat) -> None:
    """Entry point of a worker process.

    ``lifeline`` is the read end of a pipe whose only write end the API process holds: it
    reports end-of-file the moment that process is gone, however it died. ``heartbeat`` is
    a shared double where the worker stamps ``time.monotonic()`` while it can run.
    """
    # The parent stops the workers in order (after the frames already queued) on Ctrl-C or
    # SIGTERM; a worker that died of a signal sent to the whole process group first would
    # lose its frames.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    _single_threaded()
    _watch(lifeline, heartbeat)
    state = WorkerState(max_pixels=max_pixels)
    results.send(Ready(os.getpid()))
    while True:
        task = tasks.get()
        if isinstance(task, Stop):
            break
        out = state.handle(task)
        if out is not None:
            results.send(out)
    results.close()


def _watch(lifeline: Connection, heartbeat) -> None:
    """Beat the heartbeat, and end the process as soon as the API process is gone.

    A thread of its own, because the main thread may be anywhere when the API process dies:
    in a long step, or blocked for good on a task the dead process had half written into
    the queue. Exiting at once also releases the forkserver and the resource tracker,
    which stay up while any worker holds their pipes.
    """
    def run() -> None:
        while True:
            heartbeat.value = time.monotonic()
            try:
                gone = lifeline.poll(HEARTBEAT_S)  # readable only at end-of-file
            except (EOFError, OSError):
                gone = True
            if gone:
                os._exit(EXIT_ORPHANED)

    threading.Thread(target=run, name="lifeline", daemon=True).start()


def _single_threaded() -> None:
    """One thread per worker: the pool already has one worker per core."""
    try:
        import cv2

        cv2.setNumThreads(1)
    except ImportError:
        pass
