"""Engines that run the core library outside the API process.

The local engine (:class:`LocalEngine`) is a pool of worker processes on this machine: each
session is pinned to one worker so its frames run in order, maps are memory-mapped once per
(map id, revision) in every worker that needs them, and a worker that dies is replaced and
its sessions resume from their last checkpoint. The Ray engine
(:mod:`workers.engine.ray_engine`, with ``vloc[ray]``) holds sessions in shard actors of a
Ray cluster that several API processes share. Both implement :class:`Engine`.
"""

from .messages import Checkpoint, FrameDone, FrameFailed, FrameOutcome, Outcome, SessionSpec
from .pool import EngineClosed, LocalEngine, WorkerDied
from .protocol import Engine, SeqRefused, SharedEngine

__all__ = ["Checkpoint", "Engine", "EngineClosed", "FrameDone", "FrameFailed", "FrameOutcome",
           "LocalEngine", "Outcome", "SeqRefused", "SessionSpec", "SharedEngine", "WorkerDied"]
