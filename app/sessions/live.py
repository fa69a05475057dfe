"""The sessions an API process holds in memory, and their frames in flight."""

from __future__ import annotations

import asyncio
from dataclasses import dataclass, field
from datetime import datetime, timedelta

from vloc.app.db import utcnow
from vloc.app.engine import SessionSpec
from vloc.workers.core.image import Header

LAST_FRAME_MAX_BYTES = 2**20
"""A larger frame is not kept for viewers: every session would keep one until it expires."""


@dataclass(slots=True)
class Arrival:
    """A frame accepted and not answered yet."""

    t0: float
    """``time.perf_counter()`` when the frame arrived."""
    received_at: datetime
    captured_at: datetime | None
    data: bytes | None
    """The frame, until it goes to the engine."""
    queued: asyncio.Future
    """Resolves with the seq once the frame is recorded and queued in the engine."""
    previous_seq: int | None
    """The session's last seq before this frame: restored if the record fails."""
    metadata: dict | None = None
    """The frame's :class:`~workers.core.metadata.FrameMetadata`, validated."""
    size: int = 0
    """Its bytes, held in this process until it is answered (:mod:`app.sessions.budget`)."""
    header: Header | None = None
    """What its image header says (size, EXIF orientation), checked on arrival: the
    worker does not read the header again."""


@dataclass(eq=False)
class LiveSession:
    """A session this API process holds: its spec for the engine, its numbering and the
    frames it has accepted and not answered yet."""

    id: str
    token_hash: str
    spec: SessionSpec
    last_seq: int | None
    """Highest sequence number accepted (processed, queued, or recorded before a restart)."""
    arrivals: dict[int, Arrival] = field(default_factory=dict)
    """Frames accepted and not yet answered, by sequence number."""
    converged: bool = False
    """Whether an estimate converged since the start, the last reset or initial pose."""
    ttl_s: int = 3600
    last_active: datetime = field(default_factory=utcnow)
    """The last frame accepted or keep-alive; the session expires ``ttl_s`` after it."""

    follows_map: bool = False
    """Whether it moves to its map's new revision (:meth:`app.sessions.following.MapFollowing.follow`)."""
    moving: asyncio.Future | None = None
    """Resolves once a move to another revision, under way, is done (or given up)."""
    refused_revision: int | None = None
    """A revision the session could not move to: not tried again."""

    last_frame: tuple[int, bytes] | None = None
    """The latest accepted frame (seq, image bytes), for viewers; kept in memory only, and
    only up to :data:`LAST_FRAME_MAX_BYTES`."""

    def expired(self, now: datetime | None = None) -> bool:
        return (now or utcnow()) > self.last_active + timedelta(seconds=self.ttl_s)
