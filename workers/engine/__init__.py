"""Engines that run the core library outside the API process.

The local engine (:class:`LocalEngine`) is a pool of worker processes on this machine: each
session is pinned to one worker so its frames run in order, maps are memory-mapped once per
(map id, revision) in every worker that needs them, and a worker that dies is replaced and
its sessions resume from their last checkpoint.
"""

from .messages import Checkpoint, FrameDone, FrameFailed, FrameOutcome, Outcome, SessionSpec
from .pool import EngineClosed, LocalEngine, WorkerDied

__all__ = ["Checkpoint", "EngineClosed", "FrameDone", "FrameFailed", "FrameOutcome", "LocalEngine",
           "Outcome", "SessionSpec", "WorkerDied"]
