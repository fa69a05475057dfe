"""Dependencies shared by every domain: the context, a database session, the admin key."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Annotated

from fastapi import Depends
from sqlalchemy.orm import Session
from starlette.requests import HTTPConnection

from app.config import Settings
from app.context import AppContext
from app.db import session_scope
from app.problems import Problem
from app.security import matches, presented_secret

BEARER = {"WWW-Authenticate": 'Bearer realm="vloc"'}


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
    return Problem(401, detail, kind="unauthenticated", headers=BEARER)


async def require_admin(conn: HTTPConnection, ctx: Ctx) -> None:
    """The admin key, as ``Authorization: Bearer <key>`` or ``X-API-Key: <key>``.

    No credentials: 401. Credentials that are not the admin key (a session token, a wrong
    key): 403.
    """
    secret = presented_secret(conn)
    if secret is None:
        raise unauthenticated()
    if not matches(secret, ctx.admin_key_hash):
        raise Problem(403, "these credentials do not grant admin access", kind="forbidden")


AdminKey = Annotated[None, Depends(require_admin)]


def is_admin(conn: HTTPConnection, ctx: AppContext) -> bool:
    return matches(presented_secret(conn), ctx.admin_key_hash)
