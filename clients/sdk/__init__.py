"""The vloc Python client: maps, builds, sessions, frames and the pose stream.

>>> from clients import Client                                     # doctest: +SKIP
>>> with Client("http://127.0.0.1:8000", admin_key=KEY) as vloc:
...     session = vloc.create_session(map_id, mode="hybrid")
...     with vloc.stream(session) as poses:
...         vloc.send_frame(session, "frame-0001.jpg", seq=0)
...         print(next(iter(poses)))

Errors are drawn in :mod:`clients.sdk._exceptions`; :mod:`clients.sdk.testing` points a
client at the in-process app.
"""

from ._async_client import AsyncClient
from ._client import Client, SessionRef
from ._exceptions import (
    APIError,
    BadRequest,
    Conflict,
    Forbidden,
    Gone,
    JobFailed,
    NotFound,
    PayloadTooLarge,
    ProblemKind,
    ServerError,
    ServerShutdown,
    SessionDeleted,
    SessionExpired,
    StreamError,
    TooManyRequests,
    TransportError,
    Unauthorized,
    UnprocessableEntity,
    UnsupportedMediaType,
    VlocError,
    WaitTimeout,
)
from ._models import (
    Coverage,
    FlightSelfCheck,
    FrameAccepted,
    FrameError,
    GeoExtent,
    GeoPose,
    ImageRejection,
    Job,
    LocalExtent,
    Localization,
    Map,
    MapGeometry,
    MapImage,
    MapRevision,
    MapSelfCheck,
    Origin,
    Pose,
    Route,
    Session,
    SessionStats,
    UploadResult,
)
from ._requests import FRAME_METADATA, ImageSource, RetryPolicy
from ._stream import AsyncConnect, AsyncPoseStream, Connect, FrameRejected, Message, PoseStream

__all__ = [
    "FRAME_METADATA",
    "APIError", "AsyncClient", "AsyncConnect", "AsyncPoseStream", "BadRequest", "Client",
    "Coverage", "Localization",
    "Conflict", "Connect", "FlightSelfCheck", "Forbidden", "FrameAccepted", "FrameError", "FrameRejected",
    "GeoExtent", "GeoPose", "Gone", "ImageRejection", "ImageSource", "Job", "JobFailed", "LocalExtent", "Map",
    "MapGeometry", "MapImage", "MapRevision", "MapSelfCheck", "Message", "NotFound", "Origin",
    "PayloadTooLarge", "Pose", "PoseStream", "ProblemKind", "RetryPolicy", "Route",
    "ServerError",
    "ServerShutdown", "Session", "SessionDeleted", "SessionExpired", "SessionRef",
    "SessionStats", "StreamError",
    "TooManyRequests", "TransportError", "Unauthorized", "UnsupportedMediaType",
    "UploadResult", "UnprocessableEntity", "VlocError", "WaitTimeout",
]


def __getattr__(name: str):
    if name == "ValidationError":  # the old name of UnprocessableEntity
        from . import _exceptions

        return _exceptions.__getattr__(name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
