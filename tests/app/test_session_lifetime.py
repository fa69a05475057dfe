"""Session state, time to live and keep-alive, against the real app."""

from __future__ import annotations

import asyncio
import uuid
from datetime import timedelta

import pytest
from sqlalchemy import update

from tests.app.conftest import ADMIN, PROBLEM, snapshot
from tests.app.test_frames import settled
from tests.app.test_sessions import post_frame
from vloc.app.db import utcnow
from vloc.app.sessions.models import LocalisationSession


def _age(client, sid: str, seconds: float) -> None:
    """Make the session idle for ``seconds`` (its live copy and its row)."""
    ctx = client.app.state.ctx
    past = utcnow() - timedelta(seconds=seconds)
    live = ctx.sessions.find(sid)
    if live is not None:
        live.last_active = past
    with ctx.db_sessions() as db:
        db.execute(update(LocalisationSession).where(LocalisationSession.id == uuid.UUID(sid))
                   .values(last_active_at=past))
        db.commit()


def test_a_new_session_is_active_with_the_time_to_live_it_asked(service):
    c = service.client
    sid, auth = service.new_session(ttl_s=60)
    s = c.get(f"/v1/sessions/{sid}", headers=auth).json()
    assert s["state"] == "active" and s["ttl_s"] == 60
    from datetime import datetime
    left = datetime.fromisoformat(s["expires_at"]) - datetime.fromisoformat(s["last_active_at"])
    assert left == timedelta(seconds=60)
    default_sid, _ = service.new_session()
    assert c.get(f"/v1/sessions/{default_sid}", headers=ADMIN).json()["ttl_s"] == \
        c.app.state.ctx.settings.session_ttl_s


@pytest.mark.parametrize("ttl", [0, 9, 10**9, "60", 60.5])
def test_a_bad_time_to_live_is_422_and_creates_nothing(service, ttl):
    c = service.client
    before = snapshot(c)
    r = c.post("/v1/sessions", json={"map_id": service.map_id, "ttl_s": ttl}, headers=ADMIN)
    assert r.status_code == 422 and r.headers["content-type"] == PROBLEM
    assert "ttl_s" in r.text
    assert snapshot(c) == before


def test_an_idle_session_expires_and_keep_alive_prevents_it(service, shots):
    c = service.client
    sid, auth = service.new_session(ttl_s=30)
    assert post_frame(c, sid, shots[1][0].jpeg, auth, wait="true").status_code == 200
    _age(c, sid, 25)
    r = c.post(f"/v1/sessions/{sid}/keepalive", headers=auth)
    assert r.status_code == 200 and r.json()["state"] == "active"
    assert post_frame(c, sid, shots[1][1].jpeg, auth).status_code == 202  # still alive
    settled(c, sid, auth)  # a session with a frame in flight does not expire
    _age(c, sid, 31)
    r = post_frame(c, sid, shots[1][2].jpeg, auth)
    assert r.status_code == 410 and r.json()["type"].endswith("session-expired")
    s = c.get(f"/v1/sessions/{sid}", headers=auth).json()
    assert s["state"] == "expired" and s["frames_processed"] >= 1
    assert c.post(f"/v1/sessions/{sid}/keepalive", headers=auth).status_code == 410
    assert c.post(f"/v1/sessions/{sid}/reset", headers=auth).status_code == 410
    assert len(c.get(f"/v1/sessions/{sid}/poses", headers=auth).json()) >= 1
    assert sid not in c.app.state.ctx.sessions
    assert c.delete(f"/v1/sessions/{sid}", headers=auth).status_code == 204


def test_the_sweep_releases_idle_sessions_only(service, shots):
    c = service.client
    sessions = c.app.state.ctx.sessions
    idle, idle_auth = service.new_session(ttl_s=30)
    busy, busy_auth = service.new_session(ttl_s=30)
    _age(c, idle, 60)
    expired = asyncio.run_coroutine_threadsafe(sessions.expire_idle(), sessions.loop).result(30)
    assert expired >= 1
    assert idle not in sessions and busy in sessions
    assert c.get(f"/v1/sessions/{idle}", headers=idle_auth).json()["state"] == "expired"
    assert c.get(f"/v1/sessions/{busy}", headers=busy_auth).json()["state"] == "active"
