"""How a pose stream ends: a ``closed`` message that says why, then a documented close code
whose reason starts with a slug and fits a close frame -- for a deleted session (4404), an
expired one (4410, while open or at the handshake) and a server that stops (1001)."""

from __future__ import annotations

import asyncio

import pytest
from starlette.websockets import WebSocketDisconnect

from tests.app.conftest import ADMIN
from tests.app.test_session_lifetime import _age
from vloc.app.stream.router import MAX_REASON_BYTES, close_reason


def _run(client, coro):
    loop = client.app.state.ctx.intake.loop
    return asyncio.run_coroutine_threadsafe(coro, loop).result(30)


def _ending(ws) -> tuple[list[dict], int, str]:
    """The messages up to the close, the close code and its reason."""
    got = []
    with pytest.raises(WebSocketDisconnect) as closed:
        while True:
            got.append(ws.receive_json())
    return got, closed.value.code, closed.value.reason


def _whole_words(reason: str, slug: str) -> None:
    assert reason.startswith(f"{slug}: ")
    assert len(reason.encode()) <= MAX_REASON_BYTES
    assert reason.endswith(("session", "...", "back", "deleted"))


def test_deleting_a_session_ends_its_stream_with_4404(service):
    c = service.client
    sid, auth = service.new_session()
    with c.websocket_connect(f"/v1/sessions/{sid}/stream", headers=auth) as ws:
        assert ws.receive_json()["type"] == "hello"
        assert c.delete(f"/v1/sessions/{sid}", headers=ADMIN).status_code == 204
        got, code, reason = _ending(ws)
    assert [(m["type"], m["kind"]) for m in got] == [("closed", "session-deleted")]
    assert code == 4404
    _whole_words(reason, "session-deleted")


def test_an_expiring_session_ends_its_stream_with_4410(service):
    c = service.client
    sid, auth = service.new_session(ttl_s=30)
    with c.websocket_connect(f"/v1/sessions/{sid}/stream", headers=auth) as ws:
        assert ws.receive_json()["type"] == "hello"
        _age(c, sid, 60)
        assert _run(c, c.app.state.ctx.sessions.expire_idle()) >= 1
        got, code, reason = _ending(ws)
    assert [(m["type"], m["kind"]) for m in got] == [("closed", "session-expired")]
    assert "expired" in got[0]["reason"]
    assert code == 4410
    _whole_words(reason, "session-expired")


@pytest.mark.parametrize("swept", [True, False])
def test_an_expired_session_refuses_a_stream_with_4410(service, swept):
    """Whether the sweep released it already or its time to live just ran out."""
    c = service.client
    sid, auth = service.new_session(ttl_s=30)
    _age(c, sid, 60)
    if swept:
        assert _run(c, c.app.state.ctx.sessions.expire_idle()) >= 1
    with pytest.raises(WebSocketDisconnect) as closed, \
            c.websocket_connect(f"/v1/sessions/{sid}/stream", headers=auth) as ws:
        ws.receive_json()
    assert closed.value.code == 4410
    _whole_words(closed.value.reason, "session-expired")
    assert c.get(f"/v1/sessions/{sid}", headers=auth).json()["state"] == "expired"


def test_a_stopping_server_ends_the_streams_with_1001(service):
    c = service.client
    sid, auth = service.new_session()
    with c.websocket_connect(f"/v1/sessions/{sid}/stream", headers=auth) as ws:
        assert ws.receive_json()["type"] == "hello"
        _run(c, c.app.state.ctx.hub.going_away(5.0))
        got, code, reason = _ending(ws)
    assert got == [] and code == 1001
    _whole_words(reason, "server-shutdown")


def test_a_long_reason_is_cut_at_a_word():
    text = "the session could not be restored because " + "something went wrong " * 10
    reason = close_reason("session-unavailable", text)
    assert len(reason.encode()) <= MAX_REASON_BYTES and reason.endswith(" went...")
    assert close_reason("x", "short") == "x: short"
    assert len(close_reason("x", "é" * 200).encode()) <= MAX_REASON_BYTES

