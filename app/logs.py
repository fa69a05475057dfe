"""Structured logs: one JSON object per line, with a request id on request lines.

Secrets never reach a log: :class:`RedactSecrets` rewrites ``?token=...`` in URLs, bearer
credentials and ``vloc.token.`` subprotocols in every record our handler writes and every
record of uvicorn's loggers (whose WebSocket lines carry the request's full path).
"""

from __future__ import annotations

import json
import logging
import os
import re
import sys
import threading
import time
import uuid
from datetime import UTC, datetime
from urllib.parse import unquote_plus

from starlette.types import ASGIApp, Message, Receive, Scope, Send

_STANDARD = set(vars(logging.makeLogRecord({}))) | {"message", "asctime", "color_message"}
"""Record attributes that are not extra fields; ``color_message`` is uvicorn's copy of the
message with terminal colour codes, for its own console formatter only."""

access_log = logging.getLogger("vloc.access")

REDACTED = "[redacted]"
_SECRET_KEYS = frozenset({"token", "access_token", "api_key", "key"})
_QUERY_PAIR = re.compile(r"([?&])([^=&\s\"'#?]+)=([^&\s\"'#]*)")
"""A query parameter; its name is compared once percent-decoded (``tok%65n`` is ``token``
to the server that reads it)."""
_SECRETS = (
    re.compile(r"(?i)(\bbearer\s+)[^\s\"',]+"),
    re.compile(r"(?i)(\bx-api-key:\s*)[^\s\"',]+"),
    re.compile(r"(vloc\.token\.)[^\s\"',]+"),
)


def redact(text: str) -> str:
    """``text`` with every credential it carries replaced by ``[redacted]``."""
    text = _QUERY_PAIR.sub(_redact_pair, text)
    for pattern in _SECRETS:
        text = pattern.sub(r"\1" + REDACTED, text)
    return text


def _redact_pair(match: re.Match) -> str:
    sep, name, value = match.groups()
    if unquote_plus(name).strip().lower() in _SECRET_KEYS and value:
        return f"{sep}{name}={REDACTED}"
    return match.group(0)


def _redact_value(value):
    return redact(value) if isinstance(value, str) else value


class RedactSecrets(logging.Filter):
    """Redacts the message, its arguments (kept in place: uvicorn's formatters unpack
    them) and the string fields of a record."""

    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.msg, str):
            record.msg = redact(record.msg)
        if isinstance(record.args, tuple):
            record.args = tuple(_redact_value(a) for a in record.args)
        elif isinstance(record.args, dict):
            record.args = {k: _redact_value(v) for k, v in record.args.items()}
        for key, value in list(vars(record).items()):
            if key not in _STANDARD and isinstance(value, str):
                setattr(record, key, redact(value))
        return True


def redact_uvicorn() -> None:
    """Put the filter on uvicorn's own loggers, whatever handlers they write to."""
    for name in ("uvicorn.access", "uvicorn.error"):
        logger = logging.getLogger(name)
        if not any(isinstance(f, RedactSecrets) for f in logger.filters):
            logger.addFilter(RedactSecrets())


class JsonFormatter(logging.Formatter):
    """``{"ts", "level", "logger", "msg", ...extra fields}``, one line per record."""

    def format(self, record: logging.LogRecord) -> str:
        out = {"ts": datetime.fromtimestamp(record.created, UTC).isoformat(timespec="milliseconds"),
               "level": record.levelname.lower(), "logger": record.name,
               "msg": record.getMessage()}
        for key, value in vars(record).items():
            if key not in _STANDARD and not key.startswith("_"):
                out[key] = value
        if record.exc_info:
            out["exc"] = self.formatException(record.exc_info)
        return json.dumps(out, default=str)


def configure(level: str = "INFO", *, json_lines: bool = True,
              native: bool = False) -> None:
    """Send the service's and uvicorn's logs to stderr in one format.

    With ``native`` (the server's own process, never a test's), what C libraries and
    child processes write straight to file descriptor 2 (libjpeg's and libpng's warnings)
    becomes records too: see :func:`native_stderr`.
    """
    stream = native_stderr() if native and json_lines else sys.stderr
    handler = logging.StreamHandler(stream)
    handler.addFilter(RedactSecrets())
    handler.setFormatter(JsonFormatter() if json_lines else logging.Formatter(
        "%(asctime)s %(levelname)s %(name)s: %(message)s"))
    for name in ("vloc", "app", "workers", "uvicorn", "uvicorn.error"):
        logger = logging.getLogger(name)
        logger.handlers[:] = [handler]
        logger.setLevel(level.upper())
        logger.propagate = False
    # Our access log replaces uvicorn's (it carries the request id and the duration).
    logging.getLogger("uvicorn.access").disabled = True


_native_stream = None


def native_stderr():
    """The real stderr, as a text stream, after putting a pipe in place of descriptor 2.

    Every line written to the pipe (by C code, by child processes, by Python's own
    ``sys.stderr``) is read by a thread: a JSON object line goes through as it is, any
    other line becomes a ``vloc.native`` record, so the log stays JSON lines. Done once per
    process; child processes started later inherit the pipe.
    """
    global _native_stream
    if _native_stream is None:
        real = os.fdopen(os.dup(2), "w", buffering=1, encoding="utf-8", errors="replace")
        read_end, write_end = os.pipe()
        os.dup2(write_end, 2)
        os.close(write_end)
        _native_stream = real
        threading.Thread(target=_pump, args=(read_end, real), name="native-stderr",
                         daemon=True).start()
    return _native_stream


def _pump(read_end: int, real) -> None:
    native = logging.getLogger("vloc.native")
    with os.fdopen(read_end, "rb") as pipe:
        for raw in pipe:
            line = raw.decode("utf-8", "replace").rstrip()
            if not line:
                continue
            if _is_json_object(line):
                real.write(line + "\n")
            else:
                native.warning(line, extra={"source": "stderr"})


def _is_json_object(line: str) -> bool:
    if not line.startswith("{"):
        return False
    try:
        return isinstance(json.loads(line), dict)
    except ValueError:
        return False


class RequestLogMiddleware:
    """Tags every HTTP request with an ``X-Request-ID`` and logs it when it completes."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        request_id = _header(scope, b"x-request-id") or uuid.uuid4().hex
        t0 = time.perf_counter()
        status = 500

        async def send_with_id(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
                message.setdefault("headers", [])
                message["headers"] = [*message["headers"],
                                      (b"x-request-id", request_id.encode("latin-1"))]
            await send(message)

        try:
            await self.app(scope, receive, send_with_id)
        finally:
            access_log.info("request", extra={
                "method": scope["method"], "path": scope["path"], "status": status,
                "duration_ms": round((time.perf_counter() - t0) * 1e3, 3),
                "request_id": request_id})


def _header(scope: Scope, name: bytes) -> str | None:
    for key, value in scope.get("headers", ()):
        if key == name:
            return value.decode("latin-1")[:128]
    return None
