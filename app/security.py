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


TOKEN_SUBPROTOCOL = "vloc"
"""The WebSocket subprotocol the stream speaks; ``vloc.token.<token>`` beside it carries
the token where a client cannot set headers (browsers)."""
_TOKEN_PREFIX = TOKEN_SUBPROTOCOL + ".token."


def presented_secret(conn: HTTPConnection) -> str | None:
    """The credentials of a request or WebSocket handshake, None when there are none.

    ``Authorization: Bearer <secret>``, else ``X-API-Key``; a WebSocket also takes a
    ``Sec-WebSocket-Protocol`` of ``vloc, vloc.token.<token>`` and, last, ``?token=``
    (kept for old clients; access logs redact it, see :mod:`app.logs`).
    """
    secret = presented_secret_from_headers(conn.scope)
    if secret is not None or conn.scope["type"] != "websocket":
        return secret
    for protocol in conn.scope.get("subprotocols", ()):
        if protocol.startswith(_TOKEN_PREFIX) and len(protocol) > len(_TOKEN_PREFIX):
            return protocol[len(_TOKEN_PREFIX):]
    return conn.query_params.get("token") or None


def presented_secret_from_headers(scope) -> str | None:
    """``Authorization: Bearer <secret>``, else ``X-API-Key``, from an ASGI scope."""
    auth = key = None
    for name, value in scope.get("headers", ()):
        if name == b"authorization" and auth is None:
            auth = value.decode("latin-1")
        elif name == b"x-api-key" and key is None:
            key = value.decode("latin-1")
    if auth:
        scheme, _, value = auth.partition(" ")
        if scheme.lower() == "bearer" and value.strip():
            return value.strip()
    if key and key.strip():
        return key.strip()
    return None
