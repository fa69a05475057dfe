"""The pose stream's credentials: a header, a subprotocol or the (redacted) query."""

from __future__ import annotations

import pytest
from starlette.websockets import WebSocketDisconnect


def _hello(ws) -> dict:
    msg = ws.receive_json()
    assert msg["type"] == "hello"
    return msg


def test_stream_takes_the_token_in_an_authorization_header(service):
    sid, auth = service.new_session()
    with service.client.websocket_connect(f"/v1/sessions/{sid}/stream", headers=auth) as ws:
        assert _hello(ws)["session_id"] == sid


def test_stream_takes_the_token_as_a_subprotocol(service):
    sid, auth = service.new_session()
    token = auth["Authorization"].split()[1]
    with service.client.websocket_connect(
            f"/v1/sessions/{sid}/stream", subprotocols=["vloc", f"vloc.token.{token}"]) as ws:
        assert ws.accepted_subprotocol == "vloc"
        assert _hello(ws)["session_id"] == sid


@pytest.mark.parametrize("protocols", [["vloc", "vloc.token.wrong"], ["vloc", "vloc.token."]])
def test_a_wrong_or_empty_subprotocol_token_is_refused(service, protocols):
    sid, _ = service.new_session()
    with pytest.raises(WebSocketDisconnect) as info, service.client.websocket_connect(
            f"/v1/sessions/{sid}/stream", subprotocols=protocols) as ws:
        ws.receive_json()
    assert info.value.code == (4403 if protocols[1] != "vloc.token." else 4401)


def test_the_query_token_still_works(service):
    sid, auth = service.new_session()
    token = auth["Authorization"].split()[1]
    with service.client.websocket_connect(f"/v1/sessions/{sid}/stream?token={token}") as ws:
        assert _hello(ws)["session_id"] == sid


def test_frame_meta_seq_is_checked_on_a_subprotocol_stream(service, shots):
    """The token as a subprotocol, frames on the same socket: a frame_meta seq out of range
    is refused and numbers nothing; the largest seq is taken."""
    from vloc.app.sessions.schemas import MAX_SEQ

    sid, auth = service.new_session()
    token = auth["Authorization"].split()[1]
    frame = shots[1][0].jpeg
    with service.client.websocket_connect(
            f"/v1/sessions/{sid}/stream", subprotocols=["vloc", f"vloc.token.{token}"]) as ws:
        _hello(ws)
        ws.send_json({"type": "frame_meta", "seq": MAX_SEQ + 1})
        assert ws.receive_json()["problem"]["type"] == "urn:vloc:problem:bad-message"
        ws.send_json({"type": "frame_meta", "seq": MAX_SEQ,
                      "captured_at": "1970-01-02T00:00:00Z"})
        ws.send_bytes(frame)
        assert ws.receive_json()["problem"]["type"] == "urn:vloc:problem:bad-captured-at"
        ws.send_json({"type": "frame_meta", "seq": MAX_SEQ})
        ws.send_bytes(frame)
        pose = ws.receive_json()
        assert (pose["type"], pose["seq"]) == ("pose", MAX_SEQ)
