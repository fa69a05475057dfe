"""Dependencies shared by every domain: the context, a database session, the admin key."""

from __future__ import annotations

import hmac
from collections.abc import Iterator
from typing import Annotated

from fastapi import Depends, Security
from fastapi.security import APIKeyHeader, HTTPBearer
from sqlalchemy.orm import Session
from starlette.requests import HTTPConnection

from vloc.app.config import Settings
from vloc.app.context import AppContext
from vloc.app.db import session_scope
from vloc.app.problems import Problem, ProblemKind
from vloc.app.security import matches, presented_secret

BEARER = {"WWW-Authenticate": 'Bearer realm="vloc"'}

# The security schemes of the OpenAPI description. Credentials are read from the request by
# :func:`app.security.presented_secret`; these only declare where each may be sent.
admin_bearer = HTTPBearer(scheme_name="adminKey", auto_error=False,
                          description="The admin API key: `Authorization: Bearer <key>`.")
admin_header = APIKeyHeader(name="X-API-Key", scheme_name="adminApiKey", auto_error=False,
                            description="The admin API key in the `X-API-Key` header.")
session_bearer = HTTPBearer(
    scheme_name="sessionToken", auto_error=False,
    description="A session's token, returned once when the session is created: "
                "`Authorization: Bearer <token>`. The admin key opens every session too.")
metrics_bearer = HTTPBearer(
    scheme_name="metricsToken", auto_error=False,
    description="`VLOC_METRICS_TOKEN` (or the admin key): `Authorization: Bearer <token>`.")
AdminSchemes = (Security(admin_bearer), Security(admin_header))


async def get_ctx(conn: HTTPConnection) -> AppContext:
    return conn.app.state.ctx


Ctx = Annotated[AppContext, Depends(get_ctx)]


async def get_settings(ctx: Ctx) -> Settings:
    return ctx.settings


SettingsDep = Annotated[Settings, Depends(get_settings)]


def get_db(ctx: Ctx) -> Iterator[Session]:
    yield from session_scope(ctx.db_sessions)


DbSession = Annotated[Session, Depends(get_db)]


def unauthenticated(detail: str = "credentials required: Authorization: Bearer <key>") \
        -> Problem:
    return Problem(401, detail, kind=ProblemKind.UNAUTHENTICATED, headers=BEARER)


def check_admin(secret: str | None, ctx: AppContext) -> None:
    """401 without credentials; 403 for credentials that are not the admin key."""
    if secret is None:
        raise unauthenticated()
    if not matches(secret, ctx.admin_key_hash):
        raise Problem(403, "these credentials do not grant admin access", kind=ProblemKind.FORBIDDEN)


async def require_admin(conn: HTTPConnection, ctx: Ctx, _bearer=AdminSchemes[0],
                        _key=AdminSchemes[1]) -> None:
    """The admin key, as ``Authorization: Bearer <key>`` or ``X-API-Key: <key>``.

    No credentials: 401. Credentials that are not the admin key (a session token, a wrong
    key): 403.
    """
    check_admin(presented_secret(conn), ctx)


def check_metrics(secret: str | None, ctx: AppContext) -> None:
    """The metrics token or the admin key: 401 without credentials, 403 for others."""
    token = ctx.settings.metrics_token
    if secret is not None and token is not None and hmac.compare_digest(
            secret.encode("utf-8"), token.encode("utf-8")):
        return
    check_admin(secret, ctx)


async def require_metrics(conn: HTTPConnection, ctx: Ctx, _token=Security(metrics_bearer),
                          _bearer=AdminSchemes[0], _key=AdminSchemes[1]) -> None:
    check_metrics(presented_secret(conn), ctx)


AdminKey = Annotated[None, Depends(require_admin)]


def is_admin(conn: HTTPConnection, ctx: AppContext) -> bool:
    return matches(presented_secret(conn), ctx.admin_key_hash)
