"""Request-body size limits, one per kind of body.

Map-image uploads and frames have their own limits; every other route takes a small JSON
body or none. :class:`app.edge.EdgeGate` enforces them while the body arrives, before
FastAPI reads any of it.
"""

from __future__ import annotations

from enum import Enum

from starlette.requests import Request

from vloc.app.config import Settings
from vloc.app.problems import Problem, ProblemKind


class BodyKind(Enum):
    JSON = "json"
    UPLOAD = "upload"
    FRAME = "frame"


def too_large(limit: int) -> Problem:
    return Problem(413, f"request body exceeds the limit of {limit} bytes", kind=ProblemKind.TOO_LARGE,
                   limit=limit)


def body_limit(kind: BodyKind, settings: Settings) -> int:
    """Largest body in bytes: ``VLOC_MAX_JSON_BYTES``, the frame limit or the upload batch."""
    if kind is BodyKind.UPLOAD:
        return settings.request_limit_bytes
    if kind is BodyKind.FRAME:
        return settings.max_frame_bytes
    return settings.max_json_bytes


async def read_body(request: Request, limit: int) -> bytes:
    """The request's body, read in chunks; 413 as soon as it passes ``limit`` bytes."""
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > limit:
        raise too_large(limit)
    chunks, size = [], 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > limit:
            raise too_large(limit)
        chunks.append(chunk)
    return b"".join(chunks)
