"""One worker of the pool as the API process sees it, and the errors the pool raises."""

from __future__ import annotations

import multiprocessing as mp
import sys
import threading
from concurrent.futures import Future
from dataclasses import dataclass, field
from multiprocessing.connection import Connection


class WorkerDied(RuntimeError):
    """The worker process running a call or holding a frame exited."""


class EngineClosed(RuntimeError):
    """The engine is not running."""


@dataclass(eq=False)
class Slot:
    """A worker process with its task queue, its result pipe and what it holds."""

    index: int
    process: mp.process.BaseProcess
    tasks: object
    conn: Connection
    heartbeat: object
    """Shared double: ``time.monotonic()`` when the worker last ran its heartbeat."""
    ready: threading.Event = field(default_factory=threading.Event)
    broken: bool = False
    """Dead and not yet replaced: nothing may be queued on it."""
    sessions: set[str] = field(default_factory=set)
    frames: dict[tuple[str, int], None] = field(default_factory=dict)
    calls: dict[int, Future] = field(default_factory=dict)

    @property
    def load(self) -> int:
        return len(self.frames) + len(self.calls)


def remote_error(error_type: str, message: str) -> Exception:
    """Rebuild a worker's exception as the same builtin type where there is one."""
    cls = getattr(sys.modules["builtins"], error_type, None)
    if isinstance(cls, type) and issubclass(cls, Exception):
        try:
            return cls(message)
        except TypeError:
            pass
    return RuntimeError(f"{error_type}: {message}")
