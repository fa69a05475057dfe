"""The pose stream, ``WS /v1/sessions/{id}/stream``, as a blocking and an async iterator.

The server sends ``hello`` once the subscription is live, then one ``pose`` or
``frame_error`` per accepted frame in sequence order, ``error`` for a frame sent on the socket
that it refused, and ``closed`` when the session is deleted or expires. The stream is opened
only after ``hello`` has arrived, so frames posted afterwards cannot be missed.

How a stream ends is an exception, never a silent stop: :class:`SessionDeleted` (close code
4404 after ``closed``), :class:`SessionExpired` (4410), :class:`ServerShutdown` (1001). Only
the client's own ``close`` ends the iteration quietly.

The socket itself is behind a small connection interface (``send``, ``recv``, ``close``), so
tests can put the in-process app's WebSocket (Starlette's ``TestClient``) where a real
``websockets`` connection would be.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator, Awaitable, Callable, Iterator, Mapping
from dataclasses import dataclass
from datetime import datetime
from typing import Any, Protocol

from ._exceptions import (
    APIError,
    ServerShutdown,
    SessionDeleted,
    SessionExpired,
    StreamError,
    WaitTimeout,
    error_class,
)
from ._models import FrameError, Pose, parse_message
from ._requests import ImageSource, captured_at_param, image_bytes, metadata_params

NORMAL_CLOSURE = 1000


class Closed(Exception):
    """Raised by a connection's ``recv`` once the socket is closed."""

    def __init__(self, code: int | None, reason: str = "") -> None:
        super().__init__(code, reason)
        self.code = code
        self.reason = reason


class Connection(Protocol):
    """A blocking WebSocket connection; ``recv`` raises :class:`Closed` at the end and
    ``TimeoutError`` when ``timeout`` seconds pass without a message."""

    def send(self, message: str | bytes) -> None: ...

    def recv(self, timeout: float | None = None) -> str | bytes: ...

    def close(self) -> None: ...


class AsyncConnection(Protocol):
    async def send(self, message: str | bytes) -> None: ...

    async def recv(self, timeout: float | None = None) -> str | bytes: ...

    async def close(self) -> None: ...


Connect = Callable[[str, dict[str, str]], Connection]
"""``(url, headers) -> Connection``: opens a blocking WebSocket."""

AsyncConnect = Callable[[str, dict[str, str]], Awaitable[AsyncConnection]]


@dataclass(frozen=True)
class FrameRejected:
    """A frame sent on the socket that the server refused (it got no sequence number)."""

    error: APIError
    type: str = "error"


Message = Pose | FrameError | FrameRejected
_SKIP = object()


def _interpret(raw: str | bytes) -> Any:
    """One server message as what the iterator yields, or ``_SKIP``; raises the session's
    end for a ``closed`` message."""
    try:
        data = json.loads(raw)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise StreamError(f"unreadable stream message: {exc}") from None
    if not isinstance(data, dict):
        raise StreamError(f"unexpected stream message: {raw!r:.100}")
    kind = data.get("type")
    if kind == "closed":
        raise ended_error(data.get("kind") or "session-deleted",
                          str(data.get("reason") or ""))
    if kind == "error":
        problem = data.get("problem") or {}
        status = int(problem.get("status", 400))
        return FrameRejected(error_class(status)(
            status, type=problem.get("type", "about:blank"), title=problem.get("title", ""),
            detail=problem.get("detail", ""), instance=problem.get("instance"), body=problem))
    parsed = parse_message(data)
    return parsed if isinstance(parsed, Pose | FrameError) else _SKIP


def ended_error(kind: str, reason: str, code: int | None = None) -> APIError:
    """The error of a session whose stream ended: deleted or expired."""
    cls, status = (SessionExpired, 410) if kind == "session-expired" else (SessionDeleted, 404)
    return cls(status, type=f"urn:vloc:problem:{kind}", title="stream ended", detail=reason,
               body={"detail": reason, "close_code": code or 4000 + status})


def closed_error(code: int | None, reason: str, *, opened: bool = True) -> Exception | None:
    """What a close means: None for a normal end (1000); :class:`ServerShutdown` for 1001;
    :class:`SessionExpired` for 4410; for 4404, :class:`SessionDeleted` once the stream was
    open (``opened``), else NotFound; the HTTP-like error for other ``44xx`` codes (4401 ->
    Unauthorized, 4403 -> Forbidden); else StreamError."""
    if code == NORMAL_CLOSURE:
        return None
    if code == 1001:
        return ServerShutdown(reason or "the server is stopping", code=code)
    if code == 4410 or (code == 4404 and opened):
        kind = "session-expired" if code == 4410 else "session-deleted"
        return ended_error(kind, reason, code)
    if code is not None and 4400 <= code < 4600:
        status = code - 4000
        return error_class(status)(status, title="stream refused", detail=reason,
                                   body={"detail": reason, "close_code": code})
    return StreamError(reason or "the stream closed", code=code)


def frame_meta(seq: int | None, captured_at: datetime | float | str | None,
               metadata: Mapping[str, float | None] | None = None) -> str | None:
    """The text message that numbers, timestamps and describes the next binary frame."""
    extra = metadata_params(metadata)
    if seq is None and captured_at is None and not extra:
        return None
    meta: dict[str, Any] = {"type": "frame_meta"}
    if seq is not None:
        meta["seq"] = int(seq)
    if captured_at is not None:
        meta["captured_at"] = captured_at_param(captured_at)
    if extra:
        meta["metadata"] = extra
    return json.dumps(meta)


class PoseStream:
    """A session's pose stream (blocking). Use as a context manager and iterate.

    Iteration yields :class:`Pose`, :class:`FrameError` and :class:`FrameRejected` messages.
    It raises :class:`SessionDeleted` when the session is deleted, :class:`SessionExpired`
    when it expires and :class:`ServerShutdown` when the server stops; it ends quietly only
    once this side has closed the stream.

    Parameters
    ----------
    conn : Connection
    timeout : float or None
        Longest wait for one message while iterating; :class:`WaitTimeout` after it.

    Attributes
    ----------
    hello : dict
        The server's first message: ``session_id`` and ``last_seq``.
    """

    def __init__(self, conn: Connection, *, timeout: float | None = None) -> None:
        self._conn = conn
        self.timeout = timeout
        self.ended = False
        self.hello: dict = {}
        try:
            raw = self._recv(timeout if timeout is not None else 30.0)
            first = json.loads(raw)
        except BaseException:
            self.close()
            raise
        if not isinstance(first, dict) or first.get("type") != "hello":
            self.close()
            raise StreamError(f"expected the server's hello, got {raw!r:.100}")
        self.hello = first

    def _recv(self, timeout: float | None) -> str | bytes:
        try:
            return self._conn.recv(timeout)
        except Closed as c:
            self.ended = True
            error = closed_error(c.code, c.reason, opened=bool(self.hello))
            if error is not None:
                raise error from None
            raise
        except TimeoutError:
            raise WaitTimeout(f"no stream message within {timeout:g} s") from None

    def receive(self, timeout: float | None = None) -> Message | None:
        """The next message; None once the stream has ended."""
        while not self.ended:
            try:
                raw = self._recv(timeout if timeout is not None else self.timeout)
            except Closed:
                return None
            got = self._read(raw)
            if got is not _SKIP:
                return got
        return None

    def _read(self, raw: str | bytes) -> Any:
        try:
            return _interpret(raw)
        except APIError:
            self.ended = True
            raise

    def __iter__(self) -> Iterator[Message]:
        while (msg := self.receive()) is not None:
            yield msg

    def send_frame(self, image: ImageSource, *, seq: int | None = None,
                   captured_at: datetime | float | str | None = None,
                   metadata: Mapping[str, float | None] | None = None) -> None:
        """Send a JPEG/PNG frame on the socket (a path, bytes or ``(name, bytes)``); its
        estimate arrives on this stream. ``captured_at`` and ``metadata`` as for
        :meth:`Client.send_frame`."""
        data = image_bytes(image)
        meta = frame_meta(seq, captured_at, metadata)
        if meta is not None:
            self._conn.send(meta)
        self._conn.send(data)

    def ping(self) -> None:
        """Ask for a ``pong`` (skipped by the iterator; keeps idle proxies from closing)."""
        self._conn.send('{"type": "ping"}')

    def close(self) -> None:
        self.ended = True
        self._conn.close()

    def __enter__(self) -> PoseStream:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class AsyncPoseStream:
    """The async twin of :class:`PoseStream`; create it with ``await AsyncPoseStream.open``."""

    def __init__(self, conn: AsyncConnection, hello: dict, *,
                 timeout: float | None = None) -> None:
        self._conn = conn
        self.hello = hello
        self.timeout = timeout
        self.ended = False

    @classmethod
    async def open(cls, conn: AsyncConnection, *, timeout: float | None = None,
                   ) -> AsyncPoseStream:
        stream = cls(conn, {}, timeout=timeout)
        try:
            raw = await stream._recv(timeout if timeout is not None else 30.0)
            first = json.loads(raw)
        except BaseException:
            await stream.close()
            raise
        if not isinstance(first, dict) or first.get("type") != "hello":
            await stream.close()
            raise StreamError(f"expected the server's hello, got {raw!r:.100}")
        stream.hello = first
        return stream

    async def _recv(self, timeout: float | None) -> str | bytes:
        try:
            return await self._conn.recv(timeout)
        except Closed as c:
            self.ended = True
            error = closed_error(c.code, c.reason, opened=bool(self.hello))
            if error is not None:
                raise error from None
            raise
        except TimeoutError:
            raise WaitTimeout(f"no stream message within {timeout:g} s") from None

    async def receive(self, timeout: float | None = None) -> Message | None:
        while not self.ended:
            try:
                raw = await self._recv(timeout if timeout is not None else self.timeout)
            except Closed:
                return None
            got = self._read(raw)
            if got is not _SKIP:
                return got
        return None

    _read = PoseStream._read

    def __aiter__(self) -> AsyncIterator[Message]:
        return self._iterate()

    async def _iterate(self) -> AsyncIterator[Message]:
        while (msg := await self.receive()) is not None:
            yield msg

    async def send_frame(self, image: ImageSource, *, seq: int | None = None,
                         captured_at: datetime | float | str | None = None,
                         metadata: Mapping[str, float | None] | None = None) -> None:
        data = image_bytes(image)
        meta = frame_meta(seq, captured_at, metadata)
        if meta is not None:
            await self._conn.send(meta)
        await self._conn.send(data)

    async def ping(self) -> None:
        await self._conn.send('{"type": "ping"}')

    async def close(self) -> None:
        self.ended = True
        await self._conn.close()

    async def __aenter__(self) -> AsyncPoseStream:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()


# -- the websockets library ------------------------------------------------------------------

class _WebsocketsConnection:
    def __init__(self, ws) -> None:
        self._ws = ws

    def send(self, message: str | bytes) -> None:
        from websockets.exceptions import ConnectionClosed

        try:
            self._ws.send(message)
        except ConnectionClosed as exc:
            raise _closed(exc) from None

    def recv(self, timeout: float | None = None) -> str | bytes:
        from websockets.exceptions import ConnectionClosed

        try:
            return self._ws.recv(timeout)
        except ConnectionClosed as exc:
            raise _closed(exc) from None

    def close(self) -> None:
        self._ws.__exit__(None, None, None)


class _AsyncWebsocketsConnection:
    def __init__(self, ws) -> None:
        self._ws = ws

    async def send(self, message: str | bytes) -> None:
        from websockets.exceptions import ConnectionClosed

        try:
            await self._ws.send(message)
        except ConnectionClosed as exc:
            raise _closed(exc) from None

    async def recv(self, timeout: float | None = None) -> str | bytes:
        from websockets.exceptions import ConnectionClosed

        try:
            return await asyncio.wait_for(self._ws.recv(), timeout)
        except ConnectionClosed as exc:
            raise _closed(exc) from None

    async def close(self) -> None:
        await self._ws.close()


def _closed(exc) -> Closed:
    rcvd = getattr(exc, "rcvd", None)
    return Closed(rcvd.code if rcvd is not None else 1006, rcvd.reason if rcvd else str(exc))


def _handshake_error(exc: Exception) -> Exception:
    from websockets.exceptions import InvalidStatus

    from ._exceptions import TransportError

    if isinstance(exc, InvalidStatus):
        status = exc.response.status_code
        return error_class(status)(status, title="stream refused",
                                   detail=exc.response.body.decode("utf-8", "replace")[:500]
                                   if exc.response.body else "")
    return TransportError(f"cannot open the stream: {exc}")


def websockets_connect(*, open_timeout: float = 10.0) -> Connect:
    """A :data:`Connect` over the ``websockets`` library (blocking client)."""

    def connect(url: str, headers: dict[str, str]) -> Connection:
        from websockets.sync.client import connect as ws_connect

        try:
            # Entered as a context manager (left in close()): the form every websockets
            # release since 12 accepts without a deprecation warning.
            ws = ws_connect(url, additional_headers=headers, open_timeout=open_timeout,
                            max_size=2**24).__enter__()
        except Exception as exc:  # refused, timed out, or a non-101 answer
            raise _handshake_error(exc) from exc
        return _WebsocketsConnection(ws)

    return connect


def async_websockets_connect(*, open_timeout: float = 10.0) -> AsyncConnect:
    """An :data:`AsyncConnect` over the ``websockets`` library (asyncio client)."""

    async def connect(url: str, headers: dict[str, str]) -> AsyncConnection:
        from websockets.asyncio.client import connect as ws_connect

        try:
            ws = await ws_connect(url, additional_headers=headers, open_timeout=open_timeout,
                                  max_size=2**24)
        except Exception as exc:  # refused, timed out, or a non-101 answer
            raise _handshake_error(exc) from exc
        return _AsyncWebsocketsConnection(ws)

    return connect
