"""Bodies of the job routes."""

from __future__ import annotations

import uuid
from datetime import datetime
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class JobRead(BaseModel):
    model_config = ConfigDict(from_attributes=True)

    id: uuid.UUID
    map_id: uuid.UUID
    status: Literal["queued", "running", "done", "failed"] = Field(
        description="queued, running, done or failed")
    progress: float = Field(ge=0, le=1)
    stage: str | None = Field(
        None, description="What the build is doing: extracting features, extracting tie "
                          "points, matching tie points, reconstructing tiles, packing, "
                          "reconstructing the map, saving, done")
    error: str | None
    n_images: int = Field(description="Images whose features this job extracts")
    n_extracted: int
    revision: int | None = Field(description="The map revision the job produced")
    full: bool = Field(False, description="Whether the job builds the map whole (``full``): "
                                          "its geometry reconstructed and its place "
                                          "vocabularies trained afresh")
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
