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
                          JobFailed,
                          NotFound,
                          PayloadTooLarge,
                          ServerError,
                          StreamError,
                          TooManyRequests,
                          TransportError,
                          Unauthorized,
                          UnsupportedMediaType,
                          ValidationError,
                          VlocError,
                          WaitTimeout,
)
from ._models import (
                          FrameAccepted,
                          FrameError,
                          GeoExtent,
                          ImageRejection,
                          Job,
                          LocalExtent,
                          Map,
                          MapImage,
                          Origin,
                          Pose,
                          Session,
                          SessionStats,
                          UploadResult,
)
from ._requests import ImageSource, RetryPolicy
from ._stream import AsyncConnect, AsyncPoseStream, Connect, FrameRejected, Message, PoseStream

__all__ = [
    "APIError", "AsyncClient", "AsyncConnect", "AsyncPoseStream", "BadRequest", "Client",
    "Conflict", "Connect", "Forbidden", "FrameAccepted", "FrameError", "FrameRejected",
    "GeoExtent", "ImageRejection", "ImageSource", "Job", "JobFailed", "LocalExtent", "Map",
    "MapImage", "Message", "NotFound", "Origin", "PayloadTooLarge", "Pose", "PoseStream",
    "RetryPolicy", "ServerError", "Session", "SessionRef", "SessionStats", "StreamError",
    "TooManyRequests", "TransportError", "Unauthorized", "UnsupportedMediaType",
    "UploadResult", "ValidationError", "VlocError", "WaitTimeout",
]
