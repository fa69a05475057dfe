"""Tables of localisation sessions, their accepted frames and their pose estimates."""

from __future__ import annotations

import uuid
from datetime import datetime

from sqlalchemy import (
    JSON,
    BigInteger,
    Float,
    ForeignKey,
    Integer,
    LargeBinary,
    String,
    Text,
    UniqueConstraint,
)
from sqlalchemy.orm import Mapped, mapped_column

from app.db import Base, UTCDateTime, new_id, utcnow


class LocalisationSession(Base):
    __tablename__ = "sessions"

    id: Mapped[uuid.UUID] = mapped_column(primary_key=True, default=new_id)
    map_id: Mapped[uuid.UUID] = mapped_column(
        ForeignKey("maps.id", ondelete="CASCADE"), index=True)
    map_revision: Mapped[int] = mapped_column(Integer)
    """The packed map revision the session localises against, fixed at creation."""
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
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    updated_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow, onupdate=utcnow)


class Pose(Base):
    """One pose estimate of a session (Estimate fields plus the service's timing)."""

    __tablename__ = "pose_estimates"
    __table_args__ = (UniqueConstraint("session_id", "seq"),)

    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"),
                                    primary_key=True, autoincrement=True)
    session_id: Mapped[uuid.UUID] = mapped_column(
        ForeignKey("sessions.id", ondelete="CASCADE"), index=True)
    seq: Mapped[int] = mapped_column(BigInteger)
    captured_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    received_at: Mapped[datetime] = mapped_column(UTCDateTime)
    x: Mapped[float] = mapped_column(Float)
    y: Mapped[float] = mapped_column(Float)
    lat: Mapped[float] = mapped_column(Float)
    lon: Mapped[float] = mapped_column(Float)
    sigma_x: Mapped[float] = mapped_column(Float)
    sigma_y: Mapped[float] = mapped_column(Float)
    cov_xx: Mapped[float] = mapped_column(Float)
    cov_xy: Mapped[float] = mapped_column(Float)
    cov_yx: Mapped[float] = mapped_column(Float)
    cov_yy: Mapped[float] = mapped_column(Float)
    feature: Mapped[str] = mapped_column(String(32))
    next_feature: Mapped[str] = mapped_column(String(32))
    n_particles: Mapped[int] = mapped_column(Integer)
    status: Mapped[str] = mapped_column(String(16))
    best_image: Mapped[int] = mapped_column(Integer)
    decode_ms: Mapped[float] = mapped_column(Float)
    """Decoding and resizing the frame in the worker."""
    processing_ms: Mapped[float] = mapped_column(Float)
    """Time in the core's step (decoding excluded)."""
    latency_ms: Mapped[float] = mapped_column(Float)
    """From the frame's arrival at the API to its estimate's return to the API."""


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
