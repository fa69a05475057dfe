"""Tables of localisation sessions and their pose estimates."""

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
    """Highest frame sequence number processed (estimated or failed)."""
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
