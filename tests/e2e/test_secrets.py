"""A real server's log: secrets never reach it (the WebSocket line uvicorn writes carries
the query, which is redacted however its name is spelt), and it stays JSON lines when C
libraries in the server or its workers write warnings of their own."""

from __future__ import annotations

import asyncio
import json
import struct
import uuid
import zlib

import cv2
import httpx
import numpy as np
import pytest
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed

SECRET = "s3cr3t-token-that-must-not-be-logged-0123456789"


@pytest.mark.parametrize("name", ["token", "tok%65n"])
def test_tokens_in_urls_are_redacted_from_the_log(server, name):
    sid = uuid.uuid4()

    async def scenario() -> int:
        url = f"{server.ws_url}/v1/sessions/{sid}/stream?{name}={SECRET}"
        async with connect(url) as ws:
            with pytest.raises(ConnectionClosed) as info:
                await ws.recv()
        return info.value.rcvd.code

    assert asyncio.run(scenario()) == 4404
    r = httpx.get(f"{server.base_url}/v1/maps?{name}={SECRET}",
                  headers={"Authorization": f"Bearer {SECRET}"})
    assert r.status_code == 403
    server.stop()
    log = server.stderr_path.read_text()
    assert f"/v1/sessions/{sid}/stream" in log and "[redacted]" in log
    assert SECRET not in log


def png_that_libpng_warns_about() -> bytes:
    """A valid PNG with an ICC profile chunk too short to be one: Pillow reads it,
    libpng decodes it and prints a warning on stderr."""
    image = (np.random.default_rng(3).random((240, 320, 3)) * 255).astype(np.uint8)
    png = cv2.imencode(".png", image)[1].tobytes()
    body = b"iCCP" + b"prof\x00\x00" + zlib.compress(b"not a profile")
    chunk = struct.pack(">I", len(body) - 4) + body + struct.pack(">I", zlib.crc32(body))
    return png[:33] + chunk + png[33:]


def test_native_warnings_become_json_lines(server):
    admin = {"Authorization": f"Bearer {server.admin_key()}"}
    with httpx.Client(base_url=server.base_url, headers=admin, timeout=60) as http:
        map_id = http.post("/v1/maps", json={"name": "warnings"}).json()["id"]
        r = http.post(f"/v1/maps/{map_id}/images", data={"lat": "41.0", "lon": "-83.0"},
                      files=[("files", ("w.png", png_that_libpng_warns_about(), "image/png"))])
        assert r.status_code == 201, r.text
    server.stop()
    lines = server.stderr_path.read_text().splitlines()
    records = [json.loads(line) for line in lines]  # every line is one JSON object
    native = [r for r in records if r["logger"] == "vloc.native"]
    assert any("libpng warning" in r["msg"] for r in native), lines[-20:]
