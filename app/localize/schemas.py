"""The answer of a single image's localisation."""

from __future__ import annotations

from datetime import datetime
from typing import Literal

from pydantic import Field

from vloc.app.sessions.schemas import PoseFields


class Localization(PoseFields):
    """Where a single image was taken (``POST /v1/maps/{id}/localize``)."""

    type: Literal["localization"] = "localization"
    captured_at: datetime | None
    latency_ms: float = Field(description="Request arrival to answer, in the API")
