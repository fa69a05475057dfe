"""RFC 9457 problem details: every error leaves the API as ``application/problem+json``.

A :class:`Problem` raised anywhere in a request (route, dependency, service, body reader)
becomes a response with its real HTTP status; FastAPI's own validation errors and
Starlette's 404/405 are rewritten into the same shape. Its ``type`` is
``urn:vloc:problem:<kind>`` for one of the :class:`ProblemKind` slugs, which clients branch on.
"""

from __future__ import annotations

import logging
import re
from enum import StrEnum
from http import HTTPStatus

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

PROBLEM_JSON = "application/problem+json"
TYPE_PREFIX = "urn:vloc:problem:"

log = logging.getLogger(__name__)


class ProblemKind(StrEnum):
    """Every problem type the API answers with, the slug after ``urn:vloc:problem:``.

    Clients branch on these, so the list is a contract: docs/api.md says when each occurs
    (and with which status), and the SDK mirrors it (``vloc.clients.sdk.ProblemKind``);
    tests keep the three the same. Grouped by the status they usually come with.
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


class Problem(Exception):
    """An error with an HTTP status, a short title and a specific detail.

    Parameters
    ----------
    status : int
    detail : str
        What went wrong with this request, for a human.
    kind : ProblemKind or None
        Becomes the ``type`` URI ``urn:vloc:problem:<kind>``; None gives ``about:blank``.
        A slug that is not a :class:`ProblemKind` is a ValueError.
    title : str or None
        Defaults to the HTTP reason phrase.
    headers : dict or None
    **extensions
        Extra members of the problem object (RFC 9457 section 3.2).
    """

    def __init__(self, status: int, detail: str, *, kind: ProblemKind | None = None,
                 title: str | None = None, headers: dict[str, str] | None = None,
                 **extensions) -> None:
        super().__init__(detail)
        self.status = status
        self.detail = detail
        self.kind = None if kind is None else ProblemKind(kind)
        self.title = title or HTTPStatus(status).phrase
        self.headers = headers
        self.extensions = extensions

    def body(self, instance: str | None = None) -> dict:
        out = {"type": f"{TYPE_PREFIX}{self.kind}" if self.kind else "about:blank",
               "title": self.title, "status": self.status, "detail": self.detail}
        if instance:
            out["instance"] = instance
        out.update(self.extensions)
        return out


def problem_response(problem: Problem, instance: str | None = None) -> JSONResponse:
    return JSONResponse(problem.body(instance), status_code=problem.status,
                        headers=problem.headers, media_type=PROBLEM_JSON)


def not_found(what: str, ident: object) -> Problem:
    return Problem(404, f"{what} {ident} does not exist", kind=ProblemKind.NOT_FOUND)


def allowed_methods(request: Request) -> list[str] | None:
    """Every method the OpenAPI description gives the request's path, None for a path it
    does not describe.

    One path may be served by several routes, and Starlette's 405 names only the methods
    of the first of them.
    """
    templates = getattr(request.app.state, "path_methods", None)
    if templates is None:
        templates = []
        for path, operations in request.app.openapi()["paths"].items():
            pattern = re.sub(r"\\\{[^/]+?\\\}", "[^/]+", re.escape(path))
            templates.append((re.compile(f"^{pattern}$"),
                              sorted(m.upper() for m in operations if m in _HTTP_METHODS)))
        request.app.state.path_methods = templates
    for pattern, methods in templates:
        if pattern.match(request.url.path):
            return methods
    return None


_HTTP_METHODS = {"get", "put", "post", "delete", "options", "head", "patch", "trace"}


def install(app: FastAPI) -> None:
    """Register the handlers that turn every error into a problem response."""
    from vloc.app import validation_errors

    @app.exception_handler(Problem)
    async def _problem(request: Request, exc: Problem) -> JSONResponse:
        return problem_response(exc, request.url.path)

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        detail = exc.detail if isinstance(exc.detail, str) else HTTPStatus(exc.status_code).phrase
        headers = exc.headers
        if exc.status_code == 404 and detail == "Not Found":
            detail = f"no route {request.method} {request.url.path}"
        if exc.status_code == 405 and (allowed := allowed_methods(request)):
            headers = {**(headers or {}), "Allow": ", ".join(allowed)}
            detail = f"{request.method} is not allowed here; use {', '.join(allowed)}"
        return problem_response(Problem(exc.status_code, detail, headers=headers),
                                request.url.path)

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError) -> JSONResponse:
        errors = [{"loc": list(e.get("loc", ())), "msg": e.get("msg", ""),
                   "type": e.get("type", "")} for e in exc.errors()]
        route = request.scope.get("route")
        body_field = getattr(route, "body_field", None)
        errors = validation_errors.readable(
            errors, getattr(exc, "body", None),
            [body_field.field_info.annotation] if body_field is not None else [])
        first = errors[0] if errors else {"loc": [], "msg": "invalid request"}
        if first.get("type") == "missing" and tuple(first["loc"]) in validation_errors.MISSING:
            detail, kind = validation_errors.MISSING[tuple(first["loc"])]
            return problem_response(Problem(422, detail, kind=kind, errors=errors),
                                    request.url.path)
        where = ".".join(str(p) for p in first["loc"])
        detail = f"{where}: {first['msg']}" if where else first["msg"]
        if "suggestion" in first:
            detail += f"; did you mean {first['suggestion']}?"
        problem = Problem(422, detail, kind=ProblemKind.VALIDATION, errors=errors)
        return problem_response(problem, request.url.path)

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, exc: Exception) -> JSONResponse:
        log.exception("unhandled error on %s %s", request.method, request.url.path)
        return problem_response(Problem(500, "internal error; see the server log",
                                        kind=ProblemKind.INTERNAL), request.url.path)
