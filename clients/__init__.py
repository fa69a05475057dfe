"""vloc clients: the Python SDK, the ``vloc`` command line, device simulators and the
synthetic world generator."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from vloc.clients.sdk import *  # noqa: F403

# The SDK's public names, re-exported here and imported on first use, so that the command
# line and the world generator do not pay for httpx and pydantic when they do not need them.
_SDK_NAMES = frozenset({
    "APIError", "AsyncClient", "AsyncConnect", "AsyncPoseStream", "BadRequest", "Client",
    "Coverage", "Localization",
    "Conflict", "Connect", "FlightSelfCheck", "Forbidden", "FrameAccepted", "FrameError",
    "FrameRejected",
    "FRAME_METADATA", "GeoExtent", "GeoPose", "Gone", "ImageRejection", "ImageSource", "Job",
    "JobFailed", "LocalExtent", "Map", "MapGeometry", "MapImage", "MapRevision", "MapSelfCheck",
    "Message",
    "NotFound", "Origin",
    "PayloadTooLarge", "Pose", "PoseStream", "ProblemKind", "Route",
    "RetryPolicy", "ServerError", "ServerShutdown", "Session", "SessionDeleted",
    "SessionExpired", "SessionRef", "SessionStats", "StreamError",
    "TooManyRequests", "TransportError", "Unauthorized", "UnsupportedMediaType",
    "UploadResult", "UnprocessableEntity", "VlocError", "WaitTimeout",
})

__all__ = sorted(_SDK_NAMES)


def __getattr__(name: str) -> Any:
    if name in _SDK_NAMES:
        from vloc.clients import sdk

        return getattr(sdk, name)
    raise AttributeError(f"module 'clients' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | _SDK_NAMES)
