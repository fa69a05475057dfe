"""The build-job table."""

from __future__ import annotations

import uuid
from datetime import datetime

from sqlalchemy import Boolean, Float, ForeignKey, Integer, String, Text, false
from sqlalchemy.orm import Mapped, mapped_column

from vloc.app.db import Base, UTCDateTime, new_id, utcnow


class JobStatus:
    QUEUED = "queued"
    RUNNING = "running"
    DONE = "done"
    FAILED = "failed"

    ACTIVE = (QUEUED, RUNNING)


class BuildStage:
    """The stages of a build, in order, with the share of the progress bar each ends at."""

    FEATURES = "extracting features"
    TIE_POINTS = "extracting tie points"
    MATCHING = "matching tie points"
    TILES = "reconstructing tiles"
    PACKING = "packing"  # the SIFT reduction, vocabularies and reading the features
    GEOMETRY = "reconstructing the map"
    SAVING = "saving"
    DONE = "done"


class BuildJob(Base):
    __tablename__ = "build_jobs"

    id: Mapped[uuid.UUID] = mapped_column(primary_key=True, default=new_id)
    map_id: Mapped[uuid.UUID] = mapped_column(
        ForeignKey("maps.id", ondelete="CASCADE"), index=True)
    status: Mapped[str] = mapped_column(String(16), default=JobStatus.QUEUED)
    progress: Mapped[float] = mapped_column(Float, default=0.0)
    """0..1 over the whole build (:class:`BuildStage`)."""
    error: Mapped[str | None] = mapped_column(Text)
    n_images: Mapped[int] = mapped_column(Integer, default=0)
    n_extracted: Mapped[int] = mapped_column(Integer, default=0)
    stage: Mapped[str | None] = mapped_column(String(32))
    """What the build is doing now (:class:`BuildStage`); NULL before it starts."""
    revision: Mapped[int | None] = mapped_column(Integer)
    """The map revision this job produced (set when done)."""
    full: Mapped[bool] = mapped_column(Boolean, default=False, server_default=false())
    """Built whole: the geometry reconstructed and the vocabularies trained afresh, nothing
    carried over from the revision before."""
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    started_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    finished_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
