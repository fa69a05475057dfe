"""Tables of maps, their images and the images' features.

Feature arrays are stored as binary columns in little-endian byte order; each column's
docstring gives the dtype and shape so any client can read them back with
``numpy.frombuffer(data, dtype).reshape(shape)``.
"""

from __future__ import annotations

import uuid
from datetime import datetime

from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    Float,
    ForeignKey,
    Integer,
    LargeBinary,
    String,
    UniqueConstraint,
)
from sqlalchemy.orm import Mapped, mapped_column, relationship

from vloc.app.db import Base, UTCDateTime, new_id, utcnow


class MapStatus:
    EMPTY = "empty"          # no images yet
    UNBUILT = "unbuilt"      # images waiting for a build
    BUILDING = "building"
    READY = "ready"          # the current revision contains every image
    FAILED = "failed"        # the last build failed; an earlier revision may still serve


class Map(Base):
    __tablename__ = "maps"

    id: Mapped[uuid.UUID] = mapped_column(primary_key=True, default=new_id)
    name: Mapped[str] = mapped_column(String(200))
    status: Mapped[str] = mapped_column(String(16), default=MapStatus.EMPTY)
    revision: Mapped[int] = mapped_column(Integer, default=0)
    """Bumped by every successful build; 0 until the first."""
    origin_lat: Mapped[float | None] = mapped_column(Float)
    origin_lon: Mapped[float | None] = mapped_column(Float)
    origin_alt: Mapped[float | None] = mapped_column(Float)
    """Reference point of the local east-north frame of the current revision."""
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    built_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    geometry: Mapped[dict | None] = mapped_column(JSON)
    """The current revision's camera geometry: what its reconstruction placed and what the
    map measured of itself (:func:`vloc.workers.core.mapbuild.geometry_report`); NULL
    before the first build."""

    images: Mapped[list[MapImage]] = relationship(
        back_populates="map", cascade="all, delete-orphan", passive_deletes=True)


class MapRevision(Base):
    """One packed revision of a map, as its build left it: what it holds, what changed since
    the revision it was built on, and what its geometry measured of itself. A map's
    revisions stay on disk until dropped, so that the map can be restored to any of them."""

    __tablename__ = "map_revisions"

    map_id: Mapped[uuid.UUID] = mapped_column(
        ForeignKey("maps.id", ondelete="CASCADE"), primary_key=True)
    revision: Mapped[int] = mapped_column(Integer, primary_key=True)
    built_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    job_id: Mapped[uuid.UUID | None] = mapped_column()
    """The build job that packed it (no foreign key: jobs may be purged, revisions stay)."""
    base_revision: Mapped[int] = mapped_column(Integer, default=0)
    """The map's current revision when the build began (0 for the first): what ``added``
    and ``removed`` compare with."""
    image_count: Mapped[int] = mapped_column(Integer)
    added: Mapped[int] = mapped_column(Integer)
    removed: Mapped[int] = mapped_column(Integer)
    origin_lat: Mapped[float] = mapped_column(Float)
    origin_lon: Mapped[float] = mapped_column(Float)
    origin_alt: Mapped[float | None] = mapped_column(Float)
    geometry: Mapped[dict | None] = mapped_column(JSON)
    """As ``maps.geometry`` while this revision is the current one."""
    dropped_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    """When its files were deleted; the row stays, so that its number is never packed
    again (poses stored on it keep naming one revision)."""


class MapImage(Base):
    __tablename__ = "map_images"
    __table_args__ = (UniqueConstraint("map_id", "file_hash"),)

    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"),
                                    primary_key=True, autoincrement=True)
    map_id: Mapped[uuid.UUID] = mapped_column(
        ForeignKey("maps.id", ondelete="CASCADE"), index=True)
    filename: Mapped[str] = mapped_column(String(255))
    file_hash: Mapped[str] = mapped_column(String(64), index=True)
    """SHA-256 of the file, hex; also the file's name on disk. Indexed on its own: a build
    finds other maps' images of the same file by it (``BuildRunner._tie_donors``)."""
    content_type: Mapped[str] = mapped_column(String(32))
    byte_size: Mapped[int] = mapped_column(BigInteger)
    width: Mapped[int] = mapped_column(Integer)
    height: Mapped[int] = mapped_column(Integer)
    lat: Mapped[float] = mapped_column(Float)
    lon: Mapped[float] = mapped_column(Float)
    alt: Mapped[float | None] = mapped_column(Float)
    position_source: Mapped[str] = mapped_column(String(8))
    """``exif`` or ``form`` (lat/lon given with the upload)."""
    east: Mapped[float | None] = mapped_column(Float)
    north: Mapped[float | None] = mapped_column(Float)
    """Metres in the map's local frame of the last build that included the image."""
    captured_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    flight: Mapped[str | None] = mapped_column(String(64))
    """The flight (or pass) the upload said the image belongs to; NULL where it did not
    (:mod:`workers.core.flights`: grouped by capture time then)."""
    built_revision: Mapped[int | None] = mapped_column(Integer)
    """The first map revision that contained this image; NULL until then."""
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)

    map: Mapped[Map] = relationship(back_populates="images")


class ImageGlobalFeature(Base):
    """One global feature vector of one map image.

    ``data``: (dim,) float32, little-endian.
    """

    __tablename__ = "image_global_features"

    image_id: Mapped[int] = mapped_column(
        ForeignKey("map_images.id", ondelete="CASCADE"), primary_key=True)
    name: Mapped[str] = mapped_column(String(32), primary_key=True)
    dim: Mapped[int] = mapped_column(Integer)
    data: Mapped[bytes] = mapped_column(LargeBinary)


class ImageSift(Base):
    """The raw (unreduced) SIFT features of one map image.

    ``keypoints``: (n_keypoints, 4) float32, little-endian, columns x, y (pixels at the
    working resolution), size, angle (degrees).
    ``descriptors``: (n_keypoints, 128) uint8.
    """

    __tablename__ = "image_sift"

    image_id: Mapped[int] = mapped_column(
        ForeignKey("map_images.id", ondelete="CASCADE"), primary_key=True)
    n_keypoints: Mapped[int] = mapped_column(Integer)
    keypoints: Mapped[bytes] = mapped_column(LargeBinary)
    descriptors: Mapped[bytes] = mapped_column(LargeBinary)


class ImageOrb(Base):
    """The ORB features of one map image, which the place descriptors over ORB aggregate.

    ``keypoints``: (n_keypoints, 4) float32, little-endian, columns x, y (pixels at the
    working resolution), size, angle (degrees).
    ``descriptors``: (n_keypoints, 32) uint8, 256 bits per keypoint.
    """

    __tablename__ = "image_orb"

    image_id: Mapped[int] = mapped_column(
        ForeignKey("map_images.id", ondelete="CASCADE"), primary_key=True)
    n_keypoints: Mapped[int] = mapped_column(Integer)
    keypoints: Mapped[bytes] = mapped_column(LargeBinary)
    descriptors: Mapped[bytes] = mapped_column(LargeBinary)


class MapVocabulary(Base):
    """The vocabulary of one place descriptor, trained by the build of one map revision.

    A tree of ``branching ** depth`` words
    (:class:`workers.core.features.vocabulary.Vocabulary`) over local vectors of length
    ``dim`` (D), optionally projected to P principal components first.
    ``centroids``: (n_nodes, P) float32, little-endian, every node below the root level by
    level, ``n_nodes = branching + branching ** 2 + ... + branching ** depth``.
    ``idf``: (branching ** depth,) float32, little-endian.
    ``projection``: (P + 1, D) float32, little-endian, the mean and then the P principal
    axes as rows; NULL where the centres live in the vectors' own space (P = D).
    """

    __tablename__ = "map_vocabularies"

    map_id: Mapped[uuid.UUID] = mapped_column(
        ForeignKey("maps.id", ondelete="CASCADE"), primary_key=True)
    revision: Mapped[int] = mapped_column(Integer, primary_key=True)
    name: Mapped[str] = mapped_column(String(32), primary_key=True)
    """The place descriptor, e.g. ``vlad_orb``."""
    branching: Mapped[int] = mapped_column(Integer)
    depth: Mapped[int] = mapped_column(Integer)
    binary: Mapped[bool] = mapped_column(Boolean)
    """Trained by k-majority on bits (ORB)."""
    dim: Mapped[int] = mapped_column(Integer)
    centroids: Mapped[bytes] = mapped_column(LargeBinary)
    idf: Mapped[bytes] = mapped_column(LargeBinary)
    projection: Mapped[bytes | None] = mapped_column(LargeBinary)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
