"""Point a :class:`~clients.sdk.Client` at the in-process app instead of the network.

>>> from fastapi.testclient import TestClient                      # doctest: +SKIP
>>> with TestClient(create_app(settings)) as tc:                    # doctest: +SKIP
...     vloc = in_process_client(tc, admin_key=settings.admin_key)
...     with vloc.stream(session) as poses: ...

HTTP goes through the ``TestClient`` (an ``httpx.Client``), the pose stream through its
in-memory WebSocket; both run on the ``TestClient``'s event loop, where the app's lifespan
started the engine.
"""

from __future__ import annotations

from urllib.parse import urlsplit

from ._client import Client
from ._stream import Closed, Connect


class _TestClientConnection:
    def __init__(self, session) -> None:
        self._session = session
        self._closed = False

    def send(self, message: str | bytes) -> None:
        if self._closed:
            raise Closed(1006, "the socket is closed")
        if isinstance(message, str):
            self._session.send_text(message)
        else:
            self._session.send_bytes(message)

    def recv(self, timeout: float | None = None) -> str | bytes:
        if self._closed:
            raise Closed(1006, "the socket is closed")
        message = self._receive(timeout)
        if message["type"] == "websocket.close":
            self._closed = True
            raise Closed(message.get("code", 1000), message.get("reason") or "")
        return message["text"] if message.get("text") is not None else message["bytes"]

    def _receive(self, timeout: float | None) -> dict:
        if timeout is None:
            return self._session.receive()
        import anyio

        async def within() -> dict:
            with anyio.fail_after(timeout):
                return await self._session._send_rx.receive()

        return self._session.portal.call(within)

    def close(self) -> None:
        self._closed = True
        self._session.__exit__(None, None, None)


def testclient_connect(testclient) -> Connect:
    """A :data:`~clients.sdk.Connect` that opens WebSockets on a Starlette ``TestClient``."""
    from starlette.websockets import WebSocketDisconnect

    def connect(url: str, headers: dict[str, str]) -> _TestClientConnection:
        parts = urlsplit(url)
        path = parts.path + (f"?{parts.query}" if parts.query else "")
        session = testclient.websocket_connect(path, headers=dict(headers))
        try:
            session.__enter__()
        except WebSocketDisconnect as exc:
            # Closed before the handshake completed: report it as the close it is.
            return _ClosedConnection(exc.code, exc.reason or "")
        return _TestClientConnection(session)

    return connect


class _ClosedConnection:
    def __init__(self, code: int, reason: str) -> None:
        self.code, self.reason = code, reason

    def send(self, message: str | bytes) -> None:
        raise Closed(self.code, self.reason)

    def recv(self, timeout: float | None = None) -> str | bytes:
        raise Closed(self.code, self.reason)

    def close(self) -> None:
        pass


def in_process_client(testclient, *, admin_key: str | None = None, **kwargs) -> Client:
    """A Client whose HTTP and WebSocket traffic both go to ``testclient``'s app."""
    return Client(http=testclient, ws_connect=testclient_connect(testclient),
                  admin_key=admin_key, **kwargs)
