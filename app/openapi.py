"""The OpenAPI description states every response an operation can give.

FastAPI documents the success responses and a 422 in its own error shape. Every error of
this API is an RFC 9457 problem (``application/problem+json``), and the edge gate adds
responses of its own (400, 401, 403, 404, 413) before a route runs. :func:`install`
completes each operation from the rules below, so that the description and the service
agree (Schemathesis checks it in the test suite).
"""

from __future__ import annotations

from http import HTTPStatus

from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi

from vloc.app.problems import PROBLEM_JSON

PROBLEM_SCHEMA = {
    "title": "Problem",
    "type": "object",
    "description": "RFC 9457 problem details; members beyond these depend on the `type`.",
    "properties": {
        "type": {"type": "string", "description": "`urn:vloc:problem:<kind>` or about:blank"},
        "title": {"type": "string"},
        "status": {"type": "integer"},
        "detail": {"type": "string"},
        "instance": {"type": "string"},
    },
    "required": ["type", "title", "status", "detail"],
    "additionalProperties": True,
}

WHY = {
    400: "Malformed request (an invalid Content-Length header)",
    401: "No credentials",
    403: "Credentials not good for this resource",
    404: "No such resource",
    409: "Conflicts with the resource's state",
    410: "The session expired (session-expired): create a new one",
    413: "Body, file or image over the limits",
    415: "Unsupported media type",
    422: "Invalid parameters or body",
    429: "Too many: retry later (Retry-After)",
    500: "The frame was accepted and gave no estimate, or its outcome could not be stored",
    503: "Temporarily unavailable (a worker restarting or stalled, a map revision missing, "
         "the server shutting down)",
    504: "No estimate in time",
}

EXTRA = {
    ("post", "/v1/maps/{map_id}/images"): (409, 415, 503),
    ("delete", "/v1/maps/{map_id}"): (409,),
    ("delete", "/v1/maps/{map_id}/images/{image_id}"): (409,),
    ("post", "/v1/maps/{map_id}/build"): (409,),
    ("post", "/v1/sessions"): (404, 409, 429, 503),
    ("post", "/v1/sessions/{session_id}/frames"): (409, 410, 415, 429, 500, 503, 504),
    ("post", "/v1/sessions/{session_id}/reset"): (410, 503),
    ("post", "/v1/sessions/{session_id}/initial-pose"): (410, 503),
    ("post", "/v1/sessions/{session_id}/keepalive"): (410, 503),
    ("post", "/v1/maps/{map_id}/localize"): (409, 415, 500, 503, 504),
    ("get", "/readyz"): (503,),
}
"""Statuses particular to an operation, beyond those the rules in :func:`statuses` give."""


def statuses(method: str, path: str, operation: dict) -> set[int]:
    """Every error status an operation can answer with."""
    out = {400, 413}  # the gate checks every request's Content-Length
    if operation.get("security"):
        out |= {401, 403}
    if operation.get("parameters") or operation.get("requestBody"):
        out.add(422)
    if "{" in path:
        out.add(404)
    return out | set(EXTRA.get((method, path), ()))


def install(app: FastAPI) -> None:
    """Replace ``app.openapi`` with one that completes the error responses."""

    def openapi() -> dict:
        if app.openapi_schema is None:
            schema = get_openapi(title=app.title, version=app.version,
                                 description=app.description, routes=app.routes)
            complete(schema)
            app.openapi_schema = schema
        return app.openapi_schema

    app.openapi = openapi


def complete(schema: dict) -> None:
    components = schema.setdefault("components", {})
    schemas = components.setdefault("schemas", {})
    schemas["Problem"] = PROBLEM_SCHEMA
    for name in ("HTTPValidationError", "ValidationError"):
        schemas.pop(name, None)
    problem = {PROBLEM_JSON: {"schema": {"$ref": "#/components/schemas/Problem"}}}
    for path, operations in schema.get("paths", {}).items():
        for method, operation in operations.items():
            responses = operation.setdefault("responses", {})
            for status in statuses(method, path, operation):
                responses.setdefault(str(status), {})
            for code, response in responses.items():
                if code.isdigit() and int(code) >= 400:
                    response["description"] = response.get("description") or WHY.get(
                        int(code), HTTPStatus(int(code)).phrase)
                    if response["description"] == "Validation Error":
                        response["description"] = WHY[422]
                    response["content"] = dict(problem)


DOCS_ASSETS = "/docs/assets"


def serve_docs(app: FastAPI) -> None:
    """``/docs``: Swagger UI 5 (which reads OpenAPI 3.1, the version FastAPI publishes) from
    the assets of the ``fastapi-offline`` distribution, served by this app, so that the page
    works with no access to a CDN."""
    from pathlib import Path

    import fastapi_offline
    from fastapi.openapi.docs import get_swagger_ui_html
    from fastapi.responses import HTMLResponse
    from fastapi.staticfiles import StaticFiles

    assets = Path(fastapi_offline.__file__).parent / "static"
    app.mount(DOCS_ASSETS, StaticFiles(directory=assets), name="docs-assets")

    @app.get("/docs", include_in_schema=False)
    def docs() -> HTMLResponse:
        return get_swagger_ui_html(
            openapi_url=app.openapi_url, title=f"{app.title} API",
            swagger_js_url=f"{DOCS_ASSETS}/swagger-ui-bundle.js",
            swagger_css_url=f"{DOCS_ASSETS}/swagger-ui.css",
            swagger_favicon_url=f"{DOCS_ASSETS}/favicon.png",
            # no badge that asks validator.swagger.io about the description
            swagger_ui_parameters={"validatorUrl": None, "persistAuthorization": False})
