"""The edge of every HTTP request: credentials and body size, before any body is read.

FastAPI reads and parses a JSON or multipart body before it runs a route's dependencies, so
a route's own authorisation comes too late to keep large unauthenticated bodies out of the
server, and a malformed body would be answered with 422 before the missing credentials with
401. :class:`EdgeGate` runs first. It finds the policy of the request's path in
:data:`POLICIES`, checks the credentials it needs from the headers alone (the admin key, a session's token, the
metrics token), checks the declared ``Content-Length`` against the route's body limit, and
then lets the body through counted, refusing it with 413 as soon as it grows past the limit.
A refused request's body is never read: the answer carries ``Connection: close``.

The routes' own dependencies still authorise every request; the gate only makes sure that
nothing reaches them, or FastAPI's body parsing, without credentials. A test checks the
table against the security that the OpenAPI description gives every operation.
"""

from __future__ import annotations

import asyncio
import re
import uuid
from collections import OrderedDict
from dataclasses import dataclass
from enum import Enum

from sqlalchemy import select
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from vloc.app.context import AppContext
from vloc.app.deps import check_admin, check_metrics
from vloc.app.limits import BodyKind, body_limit, too_large
from vloc.app.problems import Problem, ProblemKind, not_found, problem_response
from vloc.app.security import presented_secret_from_headers
from vloc.app.sessions.dependencies import authorise
from vloc.app.sessions.models import LocalisationSession


class Access(Enum):
    PUBLIC = "public"
    ADMIN = "admin"
    SESSION = "session"
    METRICS = "metrics"


@dataclass(frozen=True, slots=True)
class Policy:
    path: re.Pattern
    methods: frozenset[str] | None
    """None: every method."""
    access: Access
    body: BodyKind = BodyKind.JSON


_ID = r"(?P<session_id>[^/]+)"
POLICIES: tuple[Policy, ...] = (
    Policy(re.compile(r"^/v1/maps/[^/]+/images$"), frozenset({"POST"}), Access.ADMIN,
           BodyKind.UPLOAD),
    Policy(re.compile(rf"^/v1/sessions/{_ID}/frames$"), frozenset({"POST"}), Access.SESSION,
           BodyKind.FRAME),
    Policy(re.compile(r"^/v1/maps/[^/]+/localize$"), frozenset({"POST"}), Access.ADMIN,
           BodyKind.FRAME),
    Policy(re.compile(r"^/v1/(maps|jobs)(/.*)?$"), None, Access.ADMIN),
    Policy(re.compile(r"^/v1/sessions/?$"), None, Access.ADMIN),
    Policy(re.compile(rf"^/v1/sessions/{_ID}(/.*)?$"), None, Access.SESSION),
    Policy(re.compile(r"^/metrics$"), None, Access.METRICS),
)
"""First match wins; a path none matches is public with a JSON body limit."""
_PUBLIC = Policy(re.compile(""), None, Access.PUBLIC)


def policy_for(method: str, path: str) -> tuple[Policy, dict[str, str]]:
    """The policy of a request and the parts of its path the policy names."""
    for policy in POLICIES:
        if policy.methods is not None and method not in policy.methods:
            continue
        match = policy.path.match(path)
        if match:
            return policy, match.groupdict()
    return _PUBLIC, {}


class TokenHashes:
    """Session id -> token hash, read from the database once per session and kept.

    A deleted session's entry may outlive it: the request then passes the gate and its
    route answers 404, as it would have anyway.
    """

    def __init__(self, size: int = 10_000) -> None:
        self.size = size
        self._known: OrderedDict[uuid.UUID, str] = OrderedDict()

    async def get(self, ctx: AppContext, session_id: uuid.UUID) -> str | None:
        found = self._known.get(session_id)
        if found is None:
            found = await asyncio.to_thread(self._read, ctx, session_id)
            if found is None:
                return None
            self._known[session_id] = found
            if len(self._known) > self.size:
                self._known.popitem(last=False)
        return found

    @staticmethod
    def _read(ctx: AppContext, session_id: uuid.UUID) -> str | None:
        with ctx.db_sessions() as db:
            return db.scalar(select(LocalisationSession.token_hash)
                             .where(LocalisationSession.id == session_id))


class EdgeGate:
    """ASGI middleware: authenticate, then bound the body, before the application reads it."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app
        self._tokens = TokenHashes()

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        ctx: AppContext = scope["app"].state.ctx
        policy, parts = policy_for(scope["method"], scope["path"])
        limit = body_limit(policy.body, ctx.settings)
        try:
            await self._authenticate(policy.access, scope, parts, ctx)
            _check_url(scope)
            declared = _content_length(scope)
        except Problem as problem:
            await _refuse(problem, scope, receive, send)
            return
        if declared is not None and declared > limit:
            await _refuse(too_large(limit), scope, receive, send)
            return
        await self._pass_counted(scope, receive, send, limit, json_body=policy.body is BodyKind.JSON and not _is_form(scope))

    async def _authenticate(self, access: Access, scope: Scope, parts: dict,
                            ctx: AppContext) -> None:
        if access is Access.PUBLIC:
            return
        secret = presented_secret_from_headers(scope)
        if access is Access.ADMIN:
            check_admin(secret, ctx)
        elif access is Access.METRICS:
            check_metrics(secret, ctx)
        else:
            await self._authenticate_session(secret, parts["session_id"], ctx)

    async def _authenticate_session(self, secret: str | None, session_id: str,
                                    ctx: AppContext) -> None:
        if secret is None:
            authorise(secret, "", ctx, session_id)  # raises the 401
        try:
            key = uuid.UUID(session_id)
        except ValueError:
            raise not_found("session", session_id) from None
        token_hash = await self._tokens.get(ctx, key)
        if token_hash is None:
            raise not_found("session", session_id)
        authorise(secret, token_hash, ctx, session_id)

    # -- the body ---------------------------------------------------------------------------

    async def _pass_counted(self, scope: Scope, receive: Receive, send: Send,
                            limit: int, *, json_body: bool = False) -> None:
        seen = 0
        refused = False
        started = False
        tail = b""

        async def counted() -> Message:
            nonlocal seen, refused, tail
            message = await receive()
            if message["type"] == "http.request":
                chunk = message.get("body", b"")
                seen += len(chunk)
                problem = too_large(limit) if seen > limit else None
                if problem is None and json_body:
                    # the tail of the previous chunk: an escape may straddle two chunks
                    if _JSON_NUL.search(tail + chunk):
                        problem = nul_problem("the JSON body")
                    tail = (tail + chunk)[-_JSON_TAIL:]
                if problem is not None:
                    if not started and not refused:
                        refused = True
                        await _refuse(problem, scope, receive, send)
                    raise problem
            return message

        async def guarded(message: Message) -> None:
            nonlocal started
            if refused:
                return  # the 413 has been sent; whatever the route made of the error is not
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, counted, guarded)
        except Problem:
            if not refused:
                raise


_JSON_NUL = re.compile(rb"(?<!\\)(?:\\\\)*\\u0000")
"""A JSON string's NUL escape: ``\u0000`` after an even number of backslashes."""
_JSON_TAIL = 64


def nul_problem(where: str) -> Problem:
    return Problem(422, f"{where} contains a NUL character; no name or value needs one",
                   kind=ProblemKind.BAD_TEXT)


def _check_url(scope: Scope) -> None:
    """422 ``bad-text`` for a NUL in the path or the query string."""
    if "\x00" in scope["path"]:
        raise nul_problem("the path")
    query = scope.get("query_string", b"")
    if b"\x00" in query or b"%00" in query:
        raise nul_problem("the query string")


def _is_form(scope: Scope) -> bool:
    """A multipart or URL-encoded form: its files are not JSON (its text fields are checked
    by the routes)."""
    for key, value in scope.get("headers", ()):
        if key == b"content-type":
            kind = value.split(b";")[0].strip().lower()
            return kind in (b"multipart/form-data", b"application/x-www-form-urlencoded")
    return False


def _content_length(scope: Scope) -> int | None:
    for key, value in scope.get("headers", ()):
        if key == b"content-length":
            if not value.isdigit():
                raise Problem(400, "invalid Content-Length header", kind=ProblemKind.BAD_REQUEST)
            return int(value)
    return None


def _has_body(scope: Scope) -> bool:
    for key, value in scope.get("headers", ()):
        if key == b"transfer-encoding" or (key == b"content-length" and value != b"0"):
            return True
    return False


async def _refuse(problem: Problem, scope: Scope, receive: Receive, send: Send) -> None:
    """Answer without reading the body; the connection closes so that it is never read."""
    response = problem_response(problem, scope["path"])
    if _has_body(scope):
        response.headers["Connection"] = "close"
    await response(scope, receive, send)
