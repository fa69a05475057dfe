"""The service's one door to the engine: every app module that starts, calls or hears from
the engine goes through here.

:func:`engine_for` picks the engine from the settings (``VLOC_ENGINE``): the local pool of
worker processes, or shard actors on a Ray cluster (``VLOC_RAY_ADDRESS``). The functions the
service runs on the engine are named here by reference, and so are the messages and errors
it reads back.
"""

from __future__ import annotations

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
from vloc.workers.engine.build import (
    decode_orb,
    decode_sift,
    decode_vector,
    decode_vocabulary,
    encode_local,
    encode_vector,
    encode_vocabulary,
    inspect_image,
)
from vloc.workers.engine.messages import DEFAULT_FACTORY

__all__ = ["DEFAULT_FACTORY", "Checkpoint", "Engine", "EngineClosed", "FrameDone", "FrameFailed", "Outcome",
           "SeqRefused", "SessionSpec", "SharedEngine", "WorkerDied", "decode_orb",
           "decode_sift", "decode_vector", "decode_vocabulary", "encode_local", "encode_vector",
           "encode_vocabulary", "inspect_image", "engine_for"]


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
                       max_pixels=settings.max_pixels, stall_s=settings.worker_stall_s)


def _deployment(settings: Settings) -> str:
    """A digest of the database the API processes share: what makes them one deployment."""
    import hashlib

    from sqlalchemy.engine import make_url

    url = make_url(settings.resolved_database_url).render_as_string(hide_password=True)
    return hashlib.blake2b(url.encode(), digest_size=6).hexdigest()
