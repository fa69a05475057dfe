"""The SDK names how a pose stream ended: :class:`SessionExpired` (HTTP 410 or close 4410),
:class:`SessionDeleted` (4404 after the stream opened), :class:`ServerShutdown` (1001);
never a silent end of the loop or a :class:`WaitTimeout`."""

from __future__ import annotations

import asyncio

import pytest

from tests.app.test_session_lifetime import _age
from tests.clients.conftest import FAST
from vloc.clients.sdk import (
    Forbidden,
    Gone,
    NotFound,
    ServerShutdown,
    SessionDeleted,
    SessionExpired,
    StreamError,
)
from vloc.clients.sdk._stream import closed_error


def _on_loop(app_client, coro):
    loop = app_client.app.state.ctx.intake.loop
    return asyncio.run_coroutine_threadsafe(coro, loop).result(30)


def test_an_expiring_session_raises_session_expired_from_the_loop(vloc, app_client,
                                                                   built_map):
    s = vloc.create_session(built_map, params=FAST, ttl_s=30)
    with vloc.stream(s, timeout=60) as poses:
        _age(app_client, s.id, 60)
        _on_loop(app_client, app_client.app.state.ctx.sessions.expire_idle())
        with pytest.raises(SessionExpired) as info:
            list(poses)
    assert isinstance(info.value, Gone) and info.value.kind == "session-expired"
    assert "create a new session" in info.value.detail


def test_an_expired_session_raises_session_expired_on_open_and_on_http(vloc, app_client,
                                                                       built_map, shots):
    s = vloc.create_session(built_map, params=FAST, ttl_s=30)
    _age(app_client, s.id, 60)
    with pytest.raises(SessionExpired) as opened:
        vloc.stream(s)
    assert opened.value.body["close_code"] == 4410
    with pytest.raises(SessionExpired):
        vloc.send_frame(s, shots[1][0].jpeg)
    with pytest.raises(SessionExpired):
        vloc.keep_alive(s)


def test_a_stopping_server_raises_server_shutdown(vloc, app_client, built_map):
    s = vloc.create_session(built_map, params=FAST)
    with vloc.stream(s, timeout=60) as poses:
        _on_loop(app_client, app_client.app.state.ctx.hub.going_away(5.0))
        with pytest.raises(ServerShutdown) as info:
            poses.receive()
    assert info.value.code == 1001 and info.value.reason.startswith("server-shutdown")
    vloc.delete_session(s)


@pytest.mark.parametrize(("code", "opened", "cls"), [
    (4404, True, SessionDeleted), (4404, False, NotFound), (4410, False, SessionExpired),
    (4410, True, SessionExpired), (1001, True, ServerShutdown), (4403, False, Forbidden),
    (1011, True, StreamError)])
def test_close_codes_map_to_named_errors(code, opened, cls):
    error = closed_error(code, "why", opened=opened)
    assert type(error) is cls
    assert closed_error(1000, "", opened=opened) is None
