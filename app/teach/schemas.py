"""Bodies of the route routes."""

from __future__ import annotations

import uuid
from datetime import datetime
from typing import Any

from pydantic import BaseModel, ConfigDict, Field


class RouteRead(BaseModel):
    model_config = ConfigDict(from_attributes=True)

    id: uuid.UUID
    map_id: uuid.UUID
    name: str
    status: str = Field(description="building, ready or failed")
    error: str | None
    params: dict[str, Any] = Field(description="Partitioning, loop-closure and relaxation "
                                               "parameters (RouteParams)")
    n_images: int
    n_nodes: int | None
    n_loops: int | None = Field(description="Loop closures found")
    length_m: float | None = Field(description="Length of the taught path")
    sweeps: int | None = Field(description="Relaxation sweeps")
    created_at: datetime
    built_at: datetime | None


class RouteNodeRead(BaseModel):
    model_config = ConfigDict(from_attributes=True)

    idx: int
    first_seq: int = Field(description="Its first (base) image in the taught sequence")
    last_seq: int
    odom_x: float
    odom_y: float
    odom_theta: float
    x: float = Field(description="Relaxed pose: east, metres in the map's local frame")
    y: float
    theta: float = Field(description="Radians counter-clockwise from east")
    variance: float


class RouteArcRead(BaseModel):
    model_config = ConfigDict(from_attributes=True)

    node_a: int
    node_b: int
    dx: float = Field(description="Position of node_b in node_a's frame, metres forward")
    dy: float = Field(description="... and metres to the left")
    dtheta: float
    variance: float
    kind: str = Field(description="odometry or loop")


class RouteImageRead(BaseModel):
    model_config = ConfigDict(from_attributes=True)

    seq: int
    image_id: int | None
    filename: str
    node: int | None
    x: float | None
    y: float | None
    theta: float | None


class RouteDetail(RouteRead):
    nodes: list[RouteNodeRead]
    arcs: list[RouteArcRead]
    images: list[RouteImageRead] = Field(description="The taught path, in driving order")
