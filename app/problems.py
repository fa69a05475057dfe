"""RFC 9457 problem details: every error leaves the API as ``application/problem+json``.

A :class:`Problem` raised anywhere in a request (route, dependency, service, body reader)
becomes a response with its real HTTP status; FastAPI's own validation errors and
Starlette's 404/405 are rewritten into the same shape.
"""

from __future__ import annotations

import logging
import re
from http import HTTPStatus

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from vloc.app import validation_errors

PROBLEM_JSON = "application/problem+json"
TYPE_PREFIX = "urn:vloc:problem:"

log = logging.getLogger(__name__)


class Problem(Exception):
    """An error with an HTTP status, a short title and a specific detail.

    Parameters
    ----------
    status : int
    detail : str
        What went wrong with this request, for a human.
    kind : str or None
        A stable slug (``bad-image``, ``stale-seq``...) that becomes the ``type`` URI
        ``urn:vloc:problem:<kind>``; None gives ``about:blank``.
    title : str or None
        Defaults to the HTTP reason phrase.
    headers : dict or None
    **extensions
        Extra members of the problem object (RFC 9457 section 3.2).
    """

    def __init__(self, status: int, detail: str, *, kind: str | None = None,
                 title: str | None = None, headers: dict[str, str] | None = None,
                 **extensions) -> None:
        super().__init__(detail)
        self.status = status
        self.detail = detail
        self.kind = kind
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
    return Problem(404, f"{what} {ident} does not exist", kind="not-found")


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
        problem = Problem(422, detail, kind="validation", errors=errors)
        return problem_response(problem, request.url.path)

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, exc: Exception) -> JSONResponse:
        log.exception("unhandled error on %s %s", request.method, request.url.path)
        return problem_response(Problem(500, "internal error; see the server log",
                                        kind="internal"), request.url.path)
