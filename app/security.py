"""Secrets: the admin key and session tokens, stored and compared as SHA-256 hashes."""

from __future__ import annotations

import hashlib
import hmac
import secrets

from starlette.requests import HTTPConnection


def hash_secret(secret: str) -> str:
    return hashlib.sha256(secret.encode("utf-8")).hexdigest()


def new_token() -> str:
    """A session token: 256 random bits, URL-safe."""
    return secrets.token_urlsafe(32)


def matches(secret: str | None, expected_hash: str) -> bool:
    """Constant-time comparison of a presented secret with a stored hash."""
    if not secret:
        return False
    return hmac.compare_digest(hash_secret(secret), expected_hash)


def presented_secret(conn: HTTPConnection) -> str | None:
    """``Authorization: Bearer <secret>``, else ``X-API-Key``, else ``?token=`` (WebSocket)."""
    auth = conn.headers.get("authorization")
    if auth:
        scheme, _, value = auth.partition(" ")
        if scheme.lower() == "bearer" and value.strip():
            return value.strip()
    key = conn.headers.get("x-api-key")
    if key:
        return key.strip()
    # Browsers cannot set headers on a WebSocket handshake, so the stream also takes the
    # token from the query; HTTP routes do not, to keep tokens out of access logs.
    if conn.scope["type"] == "websocket":
        return conn.query_params.get("token") or None
    return None
