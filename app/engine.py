"""The service's one door to the engine: every app module that starts, calls or hears from
the engine goes through here.

:func:`engine_for` picks the engine from the settings (``VLOC_ENGINE``): the local pool of
worker processes, or shard actors on a Ray cluster (``VLOC_RAY_ADDRESS``). The service runs
its own code on the engine with :func:`run_task`, which takes the functions of
:mod:`vloc.app.tasks` and no other: whatever the engine runs of the service is in that one
package, which imports no web layer. The messages and errors the service reads back are
named here too.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable

from vloc.app.config import Settings
from vloc.workers.engine import (
    Checkpoint,
    Engine,
    EngineClosed,
    FrameDone,
    FrameFailed,
    LocalEngine,
    Outcome,
    SeqRefused,
    SessionSpec,
    SharedEngine,
    WorkerDied,
)
from vloc.workers.engine.messages import DEFAULT_FACTORY

__all__ = ["DEFAULT_FACTORY", "Checkpoint", "Engine", "EngineClosed", "FrameDone", "FrameFailed",
           "Outcome", "SeqRefused", "SessionSpec", "SharedEngine", "WorkerDied", "engine_for",
           "run_task"]

TASKS = "vloc.app.tasks"
"""The package of the service's code that the engine runs."""


def engine_for(settings: Settings) -> Engine:
    """The engine the settings ask for, not started yet."""
    if settings.engine == "ray":
        try:
            from vloc.workers.engine.ray_engine import RayEngine
        except ImportError as exc:
            raise RuntimeError("VLOC_ENGINE=ray needs Ray: pip install 'vloc[ray]'") from exc
        return RayEngine(settings.ray_shards or settings.worker_count,
                         address=settings.ray_address,
                         checkpoint_every=settings.checkpoint_every,
                         max_pixels=settings.max_pixels, shard_cpus=settings.ray_shard_cpus,
                         namespace=settings.ray_namespace, hold_s=settings.ray_hold_s,
                         instance=settings.instance_name, deployment=_deployment(settings))
    return LocalEngine(settings.worker_count, checkpoint_every=settings.checkpoint_every,
                       max_pixels=settings.max_pixels, stall_s=settings.worker_stall_s,
                       preload=task_modules())


def task_modules() -> list[str]:
    """The modules of :mod:`vloc.app.tasks`: what the workers run of the service, imported
    once where they are forked from rather than by each worker's first task (with COLMAP,
    which the engine preloads itself: 0.5-0.65 s of a new worker's CPU, the database layer
    and the service's models most of it)."""
    import pkgutil

    import vloc.app.tasks as tasks

    return sorted(f"{TASKS}.{m.name}" for m in pkgutil.iter_modules(tasks.__path__))


def run_task(engine: Engine, task: Callable, /, *args, **kwargs) -> asyncio.Future:
    """Run ``task(*args, **kwargs)`` on some worker of ``engine``; await the result.

    ``task`` is a module-level function of :mod:`vloc.app.tasks` (the workers import it by
    reference); anything else is refused with a TypeError, before it reaches the engine.
    """
    module = getattr(task, "__module__", None) or ""
    qualname = getattr(task, "__qualname__", "")
    if not (callable(task) and module.startswith(TASKS + ".") and "." not in qualname):
        name = f"{module}.{qualname}" if module else repr(task)
        raise TypeError(f"the engine runs the functions of {TASKS} only, not {name}")
    return asyncio.wrap_future(engine.call(task, *args, **kwargs))


def _deployment(settings: Settings) -> str:
    """A digest of the database the API processes share: what makes them one deployment."""
    import hashlib

    from sqlalchemy.engine import make_url

    url = make_url(settings.resolved_database_url).render_as_string(hide_password=True)
    return hashlib.blake2b(url.encode(), digest_size=6).hexdigest()
