"""What the service asks of an engine, whichever runs the work.

Two engines implement it: :class:`~workers.engine.pool.LocalEngine` (worker processes of the
API process, for one server) and :class:`~workers.engine.ray_engine.RayEngine` (shard actors
on a Ray cluster, shared by every API process connected to it). The service holds an
``Engine`` and nothing more specific.

Every call that may wait on a worker returns a :class:`concurrent.futures.Future`; frame
outcomes come back through ``on_outcome``, in each session's order, on a thread of the
engine's own.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from vloc.workers.core.image import Header
    from vloc.workers.core.metadata import FrameMetadata

from collections.abc import Callable
from concurrent.futures import Future
from typing import Protocol, runtime_checkable

from .messages import Outcome, SessionSpec


@runtime_checkable
class Engine(Protocol):
    on_outcome: Callable[[Outcome], None] | None
    """Called for every frame outcome and for the state a control leaves behind."""

    shared: bool
    """True when other API processes reach the same sessions through this engine: the
    engine then numbers each session's frames (:meth:`reserve_seq`) and keeps them in order
    whichever process sent them."""

    n_workers: int
    restarts: int
    """Workers (or actors) that died and were replaced since the start."""

    # -- life cycle
    def start(self, timeout: float = ...) -> None: ...
    def close(self, timeout: float = ...) -> None: ...
    @property
    def running(self) -> bool: ...
    def alive(self) -> bool: ...
    def alive_count(self) -> int: ...

    # -- sessions
    def open_session(self, spec: SessionSpec, *, state: bytes | None = None,
                     last_seq: int | None = None) -> Future:
        """Create the session's localiser (from ``state`` when given). On a shared engine a
        session already open elsewhere is kept as it is, and ``last_seq`` (the highest seq
        the database knows) seeds the numbering."""
    def is_open(self, session_id: str) -> bool: ...
    def submit_frame(self, session_id: str, seq: int, data: bytes, *,
                     captured_at: float | None = None,
                     metadata: FrameMetadata | None = None,
                     header: Header | None = None) -> None:
        """Queue a frame; its outcome comes through ``on_outcome``. KeyError when the
        session is not open here, EngineClosed when stopped, WorkerDied while its worker
        is being replaced."""
    def pending_frames(self, session_id: str) -> int: ...
    def control(self, session_id: str, op: str, **kwargs) -> Future:
        """``reset`` / ``set_initial_pose`` / ``stats`` / ``move`` (to another revision of
        the session's map, ``spec=``), after the frames queued before."""
    def close_session(self, session_id: str) -> None: ...
    def last_state(self, session_id: str) -> bytes | None: ...

    # -- calls
    def call(self, fn: Callable, *args, **kwargs) -> Future:
        """Run a module-level function (passed by reference) on some worker."""


@runtime_checkable
class SharedEngine(Engine, Protocol):
    """An engine that several API processes share (``shared`` is True)."""

    def reserve_seq(self, session_id: str, seq: int | None) -> Future:
        """Shared engines: the frame's seq (``seq`` when it is after the last one reserved,
        else the next), held for this caller until its frame comes or it is released.
        Fails with :class:`SeqRefused` (duplicate or stale) or KeyError (not open)."""
    def release_seq(self, session_id: str, seq: int) -> None:
        """A reserved seq whose frame will not come (it could not be recorded)."""
    def live_instances(self, within_s: float) -> set[str] | None:
        """Instance names of the API processes alive in the last ``within_s`` seconds;
        None when the engine cannot tell yet."""


class SeqRefused(ValueError):
    """A frame's seq that is not after the last one reserved for its session."""

    def __init__(self, kind: str, seq: int, last_seq: int) -> None:
        super().__init__(f"seq {seq} is not after the last accepted seq {last_seq}")
        self.kind, self.seq, self.last_seq = kind, seq, last_seq
