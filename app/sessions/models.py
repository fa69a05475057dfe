"""Tables of localisation sessions, their accepted frames and their pose estimates."""

from __future__ import annotations

import uuid
from datetime import datetime

from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    Column,
    Float,
    ForeignKey,
    Integer,
    LargeBinary,
    String,
    Table,
    Text,
    UniqueConstraint,
    Uuid,
)
from sqlalchemy.orm import Mapped, mapped_column

from vloc.app.db import Base, UTCDateTime, new_id, utcnow
from vloc.app.sessions.pose import pose_columns

DEFAULT_TTL_S = 3600
"""A session's time to live when neither it nor the server's settings name one."""


class LocalisationSession(Base):
    __tablename__ = "sessions"

    id: Mapped[uuid.UUID] = mapped_column(primary_key=True, default=new_id)
    map_id: Mapped[uuid.UUID] = mapped_column(
        ForeignKey("maps.id", ondelete="CASCADE"), index=True)
    map_revision: Mapped[int] = mapped_column(Integer)
    """The packed map revision the session localises against now."""
    follows_map: Mapped[bool] = mapped_column(Boolean, default=True)
    """Whether the session moves to the map's new revision when the map is rebuilt or
    restored (false: it stays on ``map_revision``, given or current at its creation)."""
    mode: Mapped[str] = mapped_column(String(16))
    params: Mapped[dict] = mapped_column(JSON)
    """Normalised localiser parameters, defaults filled in."""
    seed: Mapped[int] = mapped_column(BigInteger)
    token_hash: Mapped[str] = mapped_column(String(64))
    """SHA-256 of the session token, hex; the token itself is shown once and never stored."""
    last_seq: Mapped[int | None] = mapped_column(BigInteger)
    """Highest frame sequence number processed (estimated or failed, interrupted included)."""
    state: Mapped[bytes | None] = mapped_column(LargeBinary)
    """Checkpointed filter state, ``Localiser.get_state()`` bytes (opaque, versioned there)."""
    state_seq: Mapped[int | None] = mapped_column(BigInteger)
    """Sequence number of the frame after which ``state`` was taken."""
    frames_processed: Mapped[int] = mapped_column(Integer, default=0)
    frames_failed: Mapped[int] = mapped_column(Integer, default=0)
    status: Mapped[str] = mapped_column(String(16), default="active", index=True)
    """``active``, or ``expired`` once idle for longer than ``ttl_s`` (frames then get 410)."""
    ttl_s: Mapped[int] = mapped_column(Integer, default=DEFAULT_TTL_S)
    """Seconds without a frame or a keep-alive after which the session expires."""
    last_active_at: Mapped[datetime | None] = mapped_column(UTCDateTime, default=utcnow)
    """The last frame accepted or keep-alive, which the time to live counts from."""
    navigation: Mapped[dict | None] = mapped_column(JSON)
    """For a session that follows a route: the route id, the follower's parameters and the
    path as it was when the session was created (``points``, ``node_s``, ``nodes``)."""
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    updated_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow, onupdate=utcnow)


class Pose(Base):
    """One pose estimate of a session: the key, and a column (or, for ``cov``, four) for
    each stored field of :class:`~app.sessions.schemas.PoseEstimate`
    (:func:`app.sessions.pose.pose_columns`)."""

    __table__ = Table(
        "pose_estimates", Base.metadata,
        Column("id", BigInteger().with_variant(Integer, "sqlite"), primary_key=True,
               autoincrement=True),
        Column("session_id", Uuid(), ForeignKey("sessions.id", ondelete="CASCADE"),
               nullable=False, index=True),
        Column("seq", BigInteger(), nullable=False),
        # the revision the estimate was made on; null for poses stored before sessions
        # followed their maps (they were made on the session's revision)
        Column("map_revision", Integer(), nullable=True),
        *pose_columns(),
        UniqueConstraint("session_id", "seq"),
    )


class FrameStatus:
    QUEUED = "queued"
    """Recorded, not answered yet."""
    ANSWERED = "answered"
    """Its estimate is stored."""
    FAILED = "failed"
    """It gave no estimate (``error_kind`` says why), and that was reported."""
    INTERRUPTED = "interrupted"
    """Its server stopped before answering it; not yet reported on a stream."""


class Frame(Base):
    """One accepted frame, recorded before it reaches a worker.

    The record is what makes a frame accepted: a server that dies with frames queued leaves
    them ``queued`` here, the next start reports them (``interrupted``) instead of
    forgetting them, and no later frame of the session is given their ``seq``.
    """

    __tablename__ = "frames"

    session_id: Mapped[uuid.UUID] = mapped_column(
        ForeignKey("sessions.id", ondelete="CASCADE"), primary_key=True)
    seq: Mapped[int] = mapped_column(BigInteger, primary_key=True, autoincrement=False)
    received_at: Mapped[datetime] = mapped_column(UTCDateTime)
    captured_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    status: Mapped[str] = mapped_column(String(16), index=True)
    owner: Mapped[str] = mapped_column(String(255))
    """The server instance that accepted it (``VLOC_INSTANCE_NAME``)."""
    error_kind: Mapped[str | None] = mapped_column(String(32))
    """For a frame that gave no estimate: the ``kind`` of its ``frame_error``."""
    error_reason: Mapped[str | None] = mapped_column(Text)
    latency_ms: Mapped[float | None] = mapped_column(Float)
    """From arrival to its outcome's return (none for an interrupted frame)."""
