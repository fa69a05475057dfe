"""Settings from the environment (``VLOC_*``), and the admin key.

Every setting has a default that runs the embedded configuration: a SQLite file and the
images under ``VLOC_DATA_DIR``, a pool of worker processes as large as the machine.
"""

from __future__ import annotations

import os
import secrets
import socket
import sys
from functools import cached_property
from pathlib import Path

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict

ADMIN_KEY_FILE = "admin_key"


class Settings(BaseSettings):
    """Service configuration; each field reads ``VLOC_<NAME>`` from the environment."""

    model_config = SettingsConfigDict(env_prefix="VLOC_", extra="ignore")

    data_dir: Path = Field(Path("data"), description="Images, packed maps, the admin key file.")
    database_url: str | None = Field(
        None, description="SQLAlchemy URL; default a SQLite file in the data directory.")
    workers: int = Field(0, ge=0, description="Worker processes; 0 means one per CPU core.")
    admin_key: str | None = Field(
        None, min_length=16, description="Admin API key; generated and stored when unset.")
    redis_url: str | None = Field(
        None, description="Redis for pose fan-out between several API replicas.")

    max_upload_bytes: int = Field(25 * 2**20, gt=0, description="Largest map image file.")
    max_files_per_upload: int = Field(200, gt=0)
    max_frame_bytes: int = Field(8 * 2**20, gt=0, description="Largest frame body.")
    max_pixels: int = Field(50_000_000, gt=0, description="Decompression-bomb guard.")
    max_pending_frames: int = Field(
        64, gt=0, description="Frames a session may have queued before 429.")
    frame_wait_timeout_s: float = Field(
        60.0, gt=0, description="How long ?wait=true waits for an estimate.")
    checkpoint_every: int = Field(
        1, ge=1, description="Store the filter state in the database every N frames.")
    worker_stall_s: float = Field(
        5.0, gt=0.5, description="A worker silent this long is not ready (/readyz 503).")
    instance_name: str = Field(
        default_factory=socket.gethostname, min_length=1, max_length=255,
        description="This server among those sharing a database: frames it left queued "
                    "are reported interrupted when it starts again.")

    auto_migrate: bool = Field(True, description="Run Alembic migrations at start-up.")
    log_level: str = "INFO"
    log_json: bool = True

    @property
    def embedded_database(self) -> bool:
        return self.database_url is None

    @cached_property
    def resolved_database_url(self) -> str:
        if self.database_url:
            return self.database_url
        return f"sqlite:///{(self.data_dir / 'vloc.sqlite3').resolve()}"

    @property
    def worker_count(self) -> int:
        if self.workers:
            return self.workers
        # The CPUs this process may run on (a container's cpuset), not the host's count.
        if hasattr(os, "sched_getaffinity"):
            return len(os.sched_getaffinity(0)) or 1
        return os.cpu_count() or 1

    @property
    def request_limit_bytes(self) -> int:
        """Largest request body of any kind: a full upload batch plus multipart overhead."""
        return self.max_upload_bytes * min(self.max_files_per_upload, 8) + 2**20

    def images_dir(self, map_id: str) -> Path:
        return self.data_dir / "maps" / map_id / "images"

    def packed_map_dir(self, map_id: str, revision: int) -> Path:
        """Where the memory-mappable :class:`~workers.core.mapdata.MapData` of a build lives."""
        return self.data_dir / "maps" / map_id / f"rev-{revision:06d}"


def ensure_admin_key(settings: Settings, *, announce=None) -> str:
    """The admin key: ``VLOC_ADMIN_KEY``, else the stored one, else a new one.

    A new key is written to ``<data_dir>/admin_key`` (mode 0600) and announced once, on the
    first start, so that the operator can copy it; later starts read the file silently.
    """
    if settings.admin_key:
        return settings.admin_key
    path = settings.data_dir / ADMIN_KEY_FILE
    if path.exists():
        return path.read_text().strip()
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    key = secrets.token_urlsafe(32)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(key + "\n")
    (announce or _print_key)(key, path)
    return key


def _print_key(key: str, path: Path) -> None:
    print(f"vloc: generated admin key (stored in {path}):\n\n    {key}\n", file=sys.stderr,
          flush=True)
