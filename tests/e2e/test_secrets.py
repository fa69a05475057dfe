"""Secrets never reach a real server's log: the WebSocket line uvicorn writes carries the
query, which is redacted."""

from __future__ import annotations

import asyncio
import uuid

import httpx
import pytest
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed

SECRET = "s3cr3t-token-that-must-not-be-logged-0123456789"


def test_tokens_in_urls_are_redacted_from_the_log(server):
    sid = uuid.uuid4()

    async def scenario() -> int:
        url = f"{server.ws_url}/v1/sessions/{sid}/stream?token={SECRET}"
        async with connect(url) as ws:
            with pytest.raises(ConnectionClosed) as info:
                await ws.recv()
        return info.value.rcvd.code

    assert asyncio.run(scenario()) == 4404
    r = httpx.get(f"{server.base_url}/v1/maps?token={SECRET}",
                  headers={"Authorization": f"Bearer {SECRET}"})
    assert r.status_code == 403
    server.stop()
    log = server.stderr_path.read_text()
    assert f"/v1/sessions/{sid}/stream" in log and "[redacted]" in log
    assert SECRET not in log
