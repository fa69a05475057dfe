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

    def __init__(self, config: uvicorn.Config, *, drain: Callable[[], Awaitable[None]]) -> None:
        super().__init__(config)
        self._drain = drain

    async def shutdown(self, sockets: list[socket.socket] | None = None) -> None:
        for server in self.servers:
            server.close()  # no new connections; the open ones carry on meanwhile
        for sock in sockets or []:
            sock.close()
        if not self.force_exit:  # a second Ctrl-C skips the drain
            await self._drain()
        await super().shutdown(sockets)
