"""Errors raised by the vloc client.

Every error the client raises is a :class:`VlocError`::

    VlocError
    ├── TransportError ........ no HTTP answer: connection refused or reset, timeout, TLS
    ├── APIError .............. the server answered with an RFC 9457 problem document
    │   ├── BadRequest ........ 400
    │   ├── Unauthorized ...... 401  no credentials, or not for this route
    │   ├── Forbidden ......... 403  credentials that do not grant this
    │   ├── NotFound .......... 404  unknown map, job, session or route
    │   │   └── SessionDeleted  the session was deleted while its stream was open (4404)
    │   ├── Conflict .......... 409  duplicate or stale frame ``seq``, map busy building
    │   ├── PayloadTooLarge ... 413
    │   ├── UnsupportedMediaType 415 not a JPEG/PNG image
    │   ├── Gone .............. 410
    │   │   └── SessionExpired  the session expired: 410 ``session-expired``, or its
    │   │                       stream closed with 4410
    │   ├── UnprocessableEntity 422  a body, query or form field the server refused
    │   ├── TooManyRequests ... 429  too many frames of the session still queued
    │   └── ServerError ....... 5xx
    ├── StreamError ........... the pose stream ended abnormally
    │   └── ServerShutdown .... the server is stopping (the stream closed with 1001)
    ├── JobFailed ............. a waited-for build job ended ``failed``
    └── WaitTimeout ........... a wait ran out of time (also a built-in ``TimeoutError``)

:func:`error_for_response` picks the class from the status code; a status without a class
of its own (418, 451...) gives a plain :class:`APIError`. Within a class, ``error.kind``
tells problems apart: one of the :class:`ProblemKind` slugs the server documents
(``error.kind == ProblemKind.STALE_SEQ``), or ``session-deleted`` for a stream that ended
because its session was deleted.
"""

from __future__ import annotations

import contextlib
import json
from enum import StrEnum
from typing import Any

import httpx


class ProblemKind(StrEnum):
    """The slug of every problem type the server answers with (after ``urn:vloc:problem:``);
    docs/api.md says when each occurs. The same list as the server's own, member for member.
    """

    BAD_REQUEST = "bad-request"
    UNAUTHENTICATED = "unauthenticated"
    FORBIDDEN = "forbidden"
    NOT_FOUND = "not-found"
    # 409
    DUPLICATE_SEQ = "duplicate-seq"
    STALE_SEQ = "stale-seq"
    SEQ_EXHAUSTED = "seq-exhausted"
    MAP_BUSY = "map-busy"
    MAP_EMPTY = "map-empty"
    MAP_IN_USE = "map-in-use"
    MAP_NOT_BUILT = "map-not-built"
    MAP_UP_TO_DATE = "map-up-to-date"
    NO_IMAGE_ACCEPTED = "no-image-accepted"
    REVISION_CURRENT = "revision-current"
    REVISION_IN_USE = "revision-in-use"
    REVISION_NOT_RESTORABLE = "revision-not-restorable"
    ROUTE_BUSY = "route-busy"
    ROUTE_NOT_READY = "route-not-ready"
    # 410
    SESSION_EXPIRED = "session-expired"
    # 413, 415
    TOO_LARGE = "too-large"
    TOO_MANY_PIXELS = "too-many-pixels"
    TOO_MANY_FILES = "too-many-files"
    UNSUPPORTED_MEDIA_TYPE = "unsupported-media-type"
    CONTENT_TYPE_MISMATCH = "content-type-mismatch"
    # 422
    EMPTY_IMAGE = "empty-image"
    BAD_IMAGE = "bad-image"
    TRUNCATED_IMAGE = "truncated-image"
    BAD_TEXT = "bad-text"
    NO_FILES = "no-files"
    NO_GPS = "no-gps"
    POSITION_AMBIGUOUS = "position-ambiguous"
    BAD_POSITION = "bad-position"
    BAD_GPS = "bad-gps"
    BAD_CAPTURED_AT = "bad-captured-at"
    BAD_ODOMETRY = "bad-odometry"
    UNKNOWN_IMAGES = "unknown-images"
    AMBIGUOUS_IMAGES = "ambiguous-images"
    BAD_METADATA = "bad-metadata"
    BAD_INITIAL_POSE = "bad-initial-pose"
    BAD_PRIOR = "bad-prior"
    BAD_CONTROL = "bad-control"
    BAD_PARAMS = "bad-params"
    VALIDATION = "validation"
    BAD_MESSAGE = "bad-message"
    # a frame accepted with ?wait=true that gave no estimate: frame-<the failure's kind>
    FRAME_BAD_IMAGE = "frame-bad-image"
    FRAME_ERROR = "frame-error"
    FRAME_NOT_STORED = "frame-not-stored"
    FRAME_WORKER_DIED = "frame-worker-died"
    FRAME_NOT_OPEN = "frame-not-open"
    # 429
    TOO_MANY_PENDING = "too-many-pending"
    TOO_MANY_SESSIONS = "too-many-sessions"
    OVER_FAIR_SHARE = "over-fair-share"
    # 500, 503, 504
    INTERNAL = "internal"
    ENGINE_UNAVAILABLE = "engine-unavailable"
    SESSION_UNAVAILABLE = "session-unavailable"
    MAP_REVISION_MISSING = "map-revision-missing"
    SHUTTING_DOWN = "shutting-down"
    STORAGE_UNAVAILABLE = "storage-unavailable"
    SERVER_BUSY = "server-busy"
    NOT_READY = "not-ready"
    ESTIMATE_TIMEOUT = "estimate-timeout"


class VlocError(Exception):
    """Base class of every error raised by the client."""


class TransportError(VlocError):
    """The request got no HTTP answer (wraps the ``httpx`` exception in ``__cause__``)."""


class APIError(VlocError):
    """A problem response (RFC 9457).

    Attributes
    ----------
    status : int
        HTTP status code.
    type : str
        Problem type URI, e.g. ``urn:vloc:problem:stale-seq``; ``about:blank`` when generic.
    title, detail : str
        Short summary and the specific explanation.
    instance : str or None
        The request path the problem occurred on.
    body : dict
        The whole problem document, extension members included (``errors``, ``last_seq``).
    """

    def __init__(self, status: int, *, type: str = "about:blank", title: str = "",
                 detail: str = "", instance: str | None = None,
                 body: dict[str, Any] | None = None) -> None:
        self.status = status
        self.type = type
        self.title = title
        self.detail = detail
        self.instance = instance
        self.body = dict(body or {})
        super().__init__(f"{status} {title}: {detail}" if detail else f"{status} {title}")

    @property
    def kind(self) -> str | None:
        """The slug of a ``urn:vloc:problem:<kind>`` type (``stale-seq``), else None."""
        prefix = "urn:vloc:problem:"
        return self.type[len(prefix):] if self.type.startswith(prefix) else None


class BadRequest(APIError):
    """400."""


class Unauthorized(APIError):
    """401: no credentials were presented, or the wrong kind."""


class Forbidden(APIError):
    """403: the credentials are valid but not for this resource."""


class NotFound(APIError):
    """404."""


class Conflict(APIError):
    """409: the request conflicts with the resource's state."""


class PayloadTooLarge(APIError):
    """413."""


class UnsupportedMediaType(APIError):
    """415."""


class SessionDeleted(NotFound):
    """The session was deleted while its stream was open (close code 4404)."""


class Gone(APIError):
    """410."""


class SessionExpired(Gone):
    """410 ``session-expired``: the session went longer than its ``ttl_s`` without a frame
    or keep-alive (HTTP, or a stream closed with 4410). Create a new session."""


class UnprocessableEntity(APIError):
    """422: a field was refused; ``body["errors"]`` lists each one where the server says,
    ``body["field"]`` names a refused frame metadata field."""


class TooManyRequests(APIError):
    """429: back off; ``retry_after`` is the server's advice in seconds, where given."""

    @property
    def retry_after(self) -> float | None:
        value = self.body.get("retry_after")
        return float(value) if isinstance(value, int | float) else None


class ServerError(APIError):
    """5xx."""


class StreamError(VlocError):
    """The pose stream was closed by the server with an error, or could not be read.

    Attributes
    ----------
    code : int or None
        The WebSocket close code, where one was received.
    reason : str
    """

    def __init__(self, reason: str, *, code: int | None = None) -> None:
        self.code = code
        self.reason = reason
        super().__init__(f"{reason} (close code {code})" if code is not None else reason)


class ServerShutdown(StreamError):
    """The server is stopping: the stream closed with 1001 after the messages of every frame
    it had accepted. Open it again once the server is back."""


class JobFailed(VlocError):
    """The build job ended with status ``failed``; ``job`` is its last state."""

    def __init__(self, job: Any) -> None:
        self.job = job
        super().__init__(f"job {job.id} failed: {job.error or 'no reason given'}")


class WaitTimeout(VlocError, TimeoutError):
    """A wait (for a job, for readiness, for a stream message) ran out of time."""


_BY_STATUS: dict[int, type[APIError]] = {
    400: BadRequest, 401: Unauthorized, 403: Forbidden, 404: NotFound, 409: Conflict,
    413: PayloadTooLarge, 415: UnsupportedMediaType, 410: Gone, 422: UnprocessableEntity,
    429: TooManyRequests,
}


_BY_KIND: dict[str, type[APIError]] = {ProblemKind.SESSION_EXPIRED: SessionExpired}


def error_class(status: int, kind: str | None = None) -> type[APIError]:
    """The :class:`APIError` subclass for an HTTP status (and problem kind)."""
    if status >= 500:
        return ServerError
    return _BY_KIND.get(kind or "", _BY_STATUS.get(status, APIError))


def error_for_response(response: httpx.Response) -> APIError:
    """Build the error for a non-2xx response, problem document or not.

    A body that is not a JSON object (a proxy's HTML error page) still gives the right
    class, with the start of the body as the detail.
    """
    try:
        body = response.json()
    except (json.JSONDecodeError, UnicodeDecodeError):
        body = None
    if not isinstance(body, dict):
        body = {"detail": response.text[:500].strip()}
    retry = response.headers.get("retry-after")
    if retry is not None and "retry_after" not in body:
        with contextlib.suppress(ValueError):
            body["retry_after"] = float(retry)
    kind = str(body.get("type") or "").removeprefix("urn:vloc:problem:")
    return error_class(response.status_code, kind)(
        response.status_code,
        type=str(body.get("type") or "about:blank"),
        title=str(body.get("title") or response.reason_phrase or ""),
        detail=str(body.get("detail") or ""),
        instance=body.get("instance"),
        body=body)


def __getattr__(name: str):
    # The 422 class was once called ValidationError, which read as pydantic's.
    if name == "ValidationError":
        import warnings

        warnings.warn("vloc.clients.sdk.ValidationError is now UnprocessableEntity",
                      DeprecationWarning, stacklevel=2)
        return UnprocessableEntity
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
