"""The uvicorn server of ``vloc serve``, with a graceful stop that drains the streams.

uvicorn on its own stops by closing every connection and only then running the
application's shutdown: frames still queued would be answered to nobody, and WebSocket
clients would see their connection drop (1006). Here a stop (SIGTERM, Ctrl-C) first
stops accepting connections, then has the application drain (:func:`app.main.drain`:
queued frames answered and stored, their messages sent, streams closed with 1001), and
then lets uvicorn finish as usual.
"""

from __future__ import annotations

import socket
from collections.abc import Awaitable, Callable

import uvicorn


class DrainingServer(uvicorn.Server):
    """``uvicorn.Server`` that awaits ``drain()`` before closing the connections."""

    def __init__(self, config: uvicorn.Config, *, drain: Callable[[], Awaitable[None]],
                 on_ready: Callable[[str], None] | None = None) -> None:
        super().__init__(config)
        self._drain = drain
        self._on_ready = on_ready

    async def startup(self, sockets: list[socket.socket] | None = None) -> None:
        await super().startup(sockets)
        if self._on_ready is not None and self.started and self.servers:
            self._on_ready(browser_url(*self.servers[0].sockets[0].getsockname()[:2]))

    async def shutdown(self, sockets: list[socket.socket] | None = None) -> None:
        for server in self.servers:
            server.close()  # no new connections; the open ones carry on meanwhile
        for sock in sockets or []:
            sock.close()
        if not self.force_exit:  # a second Ctrl-C skips the drain
            await self._drain()
        await super().shutdown(sockets)


def browser_url(host: str, port: int) -> str:
    """The address a browser on this machine opens for a server bound to ``host:port``."""
    if host in ("0.0.0.0", "::", ""):
        host = "127.0.0.1"
    return f"http://{f'[{host}]' if ':' in host else host}:{port}"
