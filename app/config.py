"""Settings from the environment (``VLOC_*``), and the admin key.

Every setting has a default that runs the embedded configuration: a SQLite file and the
images under ``VLOC_DATA_DIR``, a pool of worker processes as large as the machine.
"""

from __future__ import annotations

import math
import os
import secrets
import socket
import sys
from functools import cached_property
from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

ADMIN_KEY_FILE = "admin_key"


class Settings(BaseSettings):
    """Service configuration; each field reads ``VLOC_<NAME>`` from the environment."""

    model_config = SettingsConfigDict(env_prefix="VLOC_", extra="ignore")

    data_dir: Path = Field(Path("data"), description="Images, packed maps, the admin key file.")
    database_url: str | None = Field(
        None, description="SQLAlchemy URL; default a SQLite file in the data directory.")
    workers: int = Field(0, ge=0, description="Worker processes; 0 means one per CPU core.")
    engine: Literal["local", "ray"] = Field(
        "local", description="Where sessions run: this process's worker pool (local), or "
                             "shard actors on a Ray cluster that several API processes share "
                             "(ray; needs the vloc[ray] extra).")
    ray_address: str | None = Field(
        None, description="Ray cluster to join (e.g. ray://head:10001 or head:6379); unset "
                          "starts a cluster inside this process.")
    ray_shards: int = Field(
        0, ge=0, description="Shard actors holding the sessions (each a process); 0 means "
                             "VLOC_WORKERS. Every API process of a cluster must agree.")
    ray_namespace: str = Field(
        "vloc", min_length=1, max_length=64,
        description="Ray namespace of the shards: one per deployment sharing a cluster.")
    ray_hold_s: float = Field(
        30.0, gt=0, description="How long a shard keeps a session's later frames waiting for "
                                "a frame whose number was taken and that has not arrived (its "
                                "API process may have died).")
    ray_shard_cpus: float = Field(
        1.0, ge=0, description="CPUs the Ray scheduler reserves for each shard actor.")
    admin_key: str | None = Field(
        None, min_length=16, description="Admin API key; generated and stored when unset.")
    redis_url: str | None = Field(
        None, description="Redis for pose fan-out between several API replicas.")

    max_upload_bytes: int = Field(25 * 2**20, gt=0, description="Largest map image file.")
    max_files_per_upload: int = Field(200, gt=0)
    max_frame_bytes: int = Field(8 * 2**20, gt=0, description="Largest frame body.")
    max_json_bytes: int = Field(2**20, gt=0, description="Largest JSON (or empty) body.")
    max_pixels: int = Field(50_000_000, gt=0, description="Decompression-bomb guard.")
    map_chunk_images: int = Field(
        256, ge=1, description="Images per file of a packed revision's rows per image "
                               "(features, descriptors, 3-D points), on average: revisions "
                               "share the files an update leaves as they were (fewer, larger "
                               "files with more; finer sharing with less).")
    max_pending_frames: int = Field(
        64, gt=0, description="Frames a session may have queued before 429.")
    max_queued_bytes: int = Field(
        128 * 2**20, gt=0,
        description="Bytes of frames the API process holds at once, from their bodies' "
                    "arrival to their answers, over every session; past it frames get 503 "
                    "server-busy, and a session past its fair share of it 429 "
                    "over-fair-share, both with Retry-After. The API process's memory "
                    "stays within its idle size plus three times this "
                    "(bench/results/admission.md).")
    max_queued_frames: int = Field(
        1024, gt=0, description="Frames the API process holds at once, in the same way.")
    drain_timeout_s: float = Field(
        120.0, gt=0, description="On a graceful stop, the longest the server keeps answering "
                                 "the frames it accepted before closing the streams; it stops "
                                 "sooner once they are answered, or 10 s after the last one "
                                 "answered when the engine answers no more.")
    frame_wait_timeout_s: float = Field(
        60.0, gt=0, description="How long ?wait=true waits for an estimate.")
    checkpoint_every: int = Field(
        1, ge=1, description="Have the worker return the filter state every N frames.")
    checkpoint_interval_s: float = Field(
        2.0, ge=0, description="Store a session's filter state in the database at most once "
                               "in this many seconds (0: every state); the latest state is "
                               "kept in memory meanwhile and stored on a graceful stop. After "
                               "a crash a session resumes from a state at most this old; its "
                               "frames' records and poses are stored regardless.")
    worker_stall_s: float = Field(
        5.0, gt=0.5, description="A worker silent this long is not ready (/readyz 503).")
    instance_name: str = Field(
        default_factory=socket.gethostname, min_length=1, max_length=255,
        description="This server among those sharing a database: frames it left queued "
                    "are reported interrupted when it starts again.")
    max_sessions: int = Field(100, gt=0, description="Sessions that may exist at once.")
    session_ttl_s: int = Field(
        3600, ge=10, description="Default time to live of a session: it expires this long "
                                 "after its last frame or keep-alive.")
    max_session_ttl_s: int = Field(7 * 86400, ge=10,
                                   description="The longest time to live a session may ask.")
    converged_accuracy_m: float = Field(
        25.0, gt=0, description="A tracking estimate is converged when its 68 % horizontal "
                                "accuracy is within this many metres.")
    metrics_token: str | None = Field(
        None, min_length=16, description="Bearer token for /metrics (the admin key works too).")

    viewer_tile_url: str | None = Field(
        None, pattern=r"^https?://[^\s]*\{z\}[^\s]*\{x\}[^\s]*\{y\}[^\s]*$",
        description="Tile URL template ({z}/{x}/{y}, Web Mercator) the web viewer may draw "
                    "under a map; unset, it draws plans only. Every viewer's browser sees it.")
    viewer_tile_attribution: str = Field(
        "", max_length=500, description="Credit shown under the tiles (text).")

    auto_migrate: bool = Field(True, description="Run Alembic migrations at start-up.")
    log_level: str = "INFO"
    log_json: bool | None = Field(
        None, description="Logs as JSON lines (true) or plain text (false); unset, JSON unless "
                          "stderr is a terminal.")

    @property
    def embedded_database(self) -> bool:
        return self.database_url is None

    @cached_property
    def resolved_database_url(self) -> str:
        if self.database_url:
            return self.database_url
        return f"sqlite:///{(self.data_dir / 'vloc.sqlite3').resolve()}"

    @field_validator("admin_key", "metrics_token", "redis_url", "database_url",
                     mode="before")
    @classmethod
    def _empty_is_unset(cls, value):
        # Compose passes `VLOC_ADMIN_KEY: ${VLOC_ADMIN_KEY:-}` as an empty string.
        return None if isinstance(value, str) and not value.strip() else value

    @property
    def worker_count(self) -> int:
        if self.workers:
            return self.workers
        # The CPUs this process may run on (a container's cpuset), not the host's count,
        # and no more than its CPU quota (docker run --cpus) allows.
        if hasattr(os, "sched_getaffinity"):
            cpus = len(os.sched_getaffinity(0)) or 1
        else:
            cpus = os.cpu_count() or 1
        quota = cpu_quota()
        return max(1, min(cpus, math.ceil(quota))) if quota is not None else cpus

    @property
    def request_limit_bytes(self) -> int:
        """Largest map-image upload body: a full batch of files plus multipart overhead."""
        return self.max_upload_bytes * min(self.max_files_per_upload, 8) + 2**20

    def images_dir(self, map_id: str) -> Path:
        return self.data_dir / "maps" / map_id / "images"

    def packed_map_dir(self, map_id: str, revision: int) -> Path:
        """Where the memory-mappable :class:`~workers.core.mapdata.MapData` of a build lives."""
        return self.data_dir / "maps" / map_id / f"rev-{revision:06d}"

    def tie_store_dir(self, map_id: str) -> Path:
        """Where a map keeps its reconstruction's tie points and matched pairs from build to
        build (about 430 kB an image), so that a rebuild matches only what changed."""
        return self.data_dir / "maps" / map_id / "ties"


CGROUP_CPU_MAX = Path("/sys/fs/cgroup/cpu.max")
CGROUP_V1_QUOTA = Path("/sys/fs/cgroup/cpu/cpu.cfs_quota_us")
CGROUP_V1_PERIOD = Path("/sys/fs/cgroup/cpu/cpu.cfs_period_us")


def cpu_quota(cpu_max: Path = CGROUP_CPU_MAX, v1_quota: Path = CGROUP_V1_QUOTA,
              v1_period: Path = CGROUP_V1_PERIOD) -> float | None:
    """CPUs' worth of time the cgroup may use (``docker run --cpus``), or None without a
    quota: ``cpu.max`` (cgroup v2, "QUOTA PERIOD" or "max PERIOD"), else the v1 files."""
    try:
        quota, period = cpu_max.read_text().split()[:2]
        return None if quota == "max" else int(quota) / int(period)
    except (OSError, ValueError):
        pass
    try:
        quota_us, period_us = int(v1_quota.read_text()), int(v1_period.read_text())
    except (OSError, ValueError):
        return None
    return quota_us / period_us if quota_us > 0 and period_us > 0 else None


def private_dir(path: Path) -> None:
    """Create ``path`` readable by this user alone (0700), or make it so when it is ours."""
    path.mkdir(mode=0o700, parents=True, exist_ok=True)
    if path.stat().st_uid == os.getuid() and path.stat().st_mode & 0o077:
        path.chmod(0o700)


def ensure_admin_key(settings: Settings, *, announce=None) -> str:
    """The admin key: ``VLOC_ADMIN_KEY``, else the stored one, else a new one.

    A new key is written to ``<data_dir>/admin_key`` (mode 0600); its file (not the key) is
    announced once, on the first start; later starts read the file silently.
    """
    if settings.admin_key:
        return settings.admin_key
    path = settings.data_dir / ADMIN_KEY_FILE
    if path.exists():
        return path.read_text().strip()
    private_dir(settings.data_dir)
    key = secrets.token_urlsafe(32)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(key + "\n")
    (announce or _print_key)(key, path)
    return key


def _print_key(key: str, path: Path) -> None:
    # The key itself never goes to stderr: that is where the logs go, and logs are
    # collected and kept. The operator reads it from the file.
    del key
    print(f"vloc: generated an admin key; it is in {path} (readable by this user only)",
          file=sys.stderr, flush=True)
