"""Request-body size limits, enforced while the body arrives (not after it is stored)."""

from __future__ import annotations

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from app.problems import Problem, problem_response


def too_large(limit: int) -> Problem:
    return Problem(413, f"request body exceeds the limit of {limit} bytes", kind="too-large",
                   limit=limit)


class BodySizeLimitMiddleware:
    """Refuse bodies over ``limit`` bytes: by Content-Length up front, else while streaming."""

    def __init__(self, app: ASGIApp, limit: int) -> None:
        self.app = app
        self.limit = limit

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        for key, value in scope.get("headers", ()):
            if key == b"content-length":
                try:
                    declared = int(value)
                except ValueError:
                    declared = -1
                if declared > self.limit or declared < 0:
                    problem = too_large(self.limit) if declared > self.limit else Problem(
                        400, "invalid Content-Length header", kind="bad-request")
                    await problem_response(problem, scope["path"])(scope, receive, send)
                    return
        seen = 0

        async def counted() -> Message:
            nonlocal seen
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > self.limit:
                    raise too_large(self.limit)
            return message

        await self.app(scope, counted, send)
