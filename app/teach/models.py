"""Tables of route maps: the taught sequence, its topological nodes and arcs.

A route belongs to a map: its images are the map's images, in the order they were taken on
the taught drive, each with its odometry pose. Building the route fills in the node of each
image and its relaxed pose (the taught path), the nodes and the arcs.
"""

from __future__ import annotations

import uuid
from datetime import datetime

from sqlalchemy import JSON, BigInteger, Float, ForeignKey, Integer, String, Text
from sqlalchemy.orm import Mapped, mapped_column

from vloc.app.db import Base, UTCDateTime, new_id, utcnow

_IMAGE_ID = BigInteger().with_variant(Integer, "sqlite")


class RouteStatus:
    BUILDING = "building"
    READY = "ready"
    FAILED = "failed"


class Route(Base):
    __tablename__ = "routes"

    id: Mapped[uuid.UUID] = mapped_column(primary_key=True, default=new_id)
    map_id: Mapped[uuid.UUID] = mapped_column(ForeignKey("maps.id", ondelete="CASCADE"),
                                              index=True)
    name: Mapped[str] = mapped_column(String(200))
    status: Mapped[str] = mapped_column(String(16), default=RouteStatus.BUILDING)
    error: Mapped[str | None] = mapped_column(Text)
    params: Mapped[dict] = mapped_column(JSON)
    """:class:`workers.core.navigation.RouteParams` fields."""
    n_images: Mapped[int] = mapped_column(Integer)
    n_nodes: Mapped[int | None] = mapped_column(Integer)
    n_loops: Mapped[int | None] = mapped_column(Integer)
    """Loop-closure arcs found."""
    length_m: Mapped[float | None] = mapped_column(Float)
    """Length of the relaxed taught path."""
    sweeps: Mapped[int | None] = mapped_column(Integer)
    """Relaxation sweeps run."""
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    built_at: Mapped[datetime | None] = mapped_column(UTCDateTime)


class RouteImage(Base):
    """One image of the taught sequence, in driving order (``seq`` from 0)."""

    __tablename__ = "route_images"

    route_id: Mapped[uuid.UUID] = mapped_column(ForeignKey("routes.id", ondelete="CASCADE"),
                                                primary_key=True)
    seq: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=False)
    image_id: Mapped[int | None] = mapped_column(
        _IMAGE_ID, ForeignKey("map_images.id", ondelete="SET NULL"))
    """NULL once the map image is deleted; the built route keeps its geometry."""
    filename: Mapped[str] = mapped_column(String(255))
    odom_x: Mapped[float] = mapped_column(Float)
    odom_y: Mapped[float] = mapped_column(Float)
    odom_theta: Mapped[float] = mapped_column(Float)
    """Odometry pose, metres and radians counter-clockwise from the odometry x axis."""
    lat: Mapped[float | None] = mapped_column(Float)
    lon: Mapped[float | None] = mapped_column(Float)
    """GPS given with the odometry, if any."""
    node: Mapped[int | None] = mapped_column(Integer)
    x: Mapped[float | None] = mapped_column(Float)
    y: Mapped[float | None] = mapped_column(Float)
    theta: Mapped[float | None] = mapped_column(Float)
    """Pose on the taught path after relaxation, in the map's local frame where the map's
    positions allowed aligning it (east, north, radians from east)."""


class RouteNode(Base):
    """A topological node: a local map whose base is its first image."""

    __tablename__ = "route_nodes"

    route_id: Mapped[uuid.UUID] = mapped_column(ForeignKey("routes.id", ondelete="CASCADE"),
                                                primary_key=True)
    idx: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=False)
    first_seq: Mapped[int] = mapped_column(Integer)
    last_seq: Mapped[int] = mapped_column(Integer)
    odom_x: Mapped[float] = mapped_column(Float)
    odom_y: Mapped[float] = mapped_column(Float)
    odom_theta: Mapped[float] = mapped_column(Float)
    x: Mapped[float] = mapped_column(Float)
    y: Mapped[float] = mapped_column(Float)
    theta: Mapped[float] = mapped_column(Float)
    variance: Mapped[float] = mapped_column(Float)


class RouteArc(Base):
    """A relation between two nodes: the pose of ``node_b`` in ``node_a``'s frame."""

    __tablename__ = "route_arcs"

    route_id: Mapped[uuid.UUID] = mapped_column(ForeignKey("routes.id", ondelete="CASCADE"),
                                                primary_key=True)
    idx: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=False)
    node_a: Mapped[int] = mapped_column(Integer)
    node_b: Mapped[int] = mapped_column(Integer)
    dx: Mapped[float] = mapped_column(Float)
    dy: Mapped[float] = mapped_column(Float)
    dtheta: Mapped[float] = mapped_column(Float)
    variance: Mapped[float] = mapped_column(Float)
    kind: Mapped[str] = mapped_column(String(16))
    """``odometry`` (consecutive nodes) or ``loop`` (a place recognised again)."""
