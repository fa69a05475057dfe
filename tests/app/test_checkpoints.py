"""Checkpoints at a bounded rate: a session's filter state (tens of kilobytes) is stored at
most once per VLOC_CHECKPOINT_INTERVAL_S, the latest one kept in memory meanwhile and stored
on a graceful stop, from which the session resumes after a restart; every frame's record
and pose are stored as before."""

from __future__ import annotations

import uuid

import pytest
from fastapi.testclient import TestClient

from tests.app.conftest import ADMIN, FAST, build_map, service_settings
from tests.app.test_sessions import post_frame
from tests.conftest import postgres_schema_url
from vloc.app.main import create_app
from vloc.app.sessions.models import LocalisationSession


def _state(client: TestClient, sid: str) -> tuple[int | None, int]:
    with client.app.state.ctx.db_sessions() as db:
        row = db.get(LocalisationSession, uuid.UUID(sid))
        return row.state_seq, row.frames_processed


@pytest.mark.parametrize("backend", ["sqlite", pytest.param("postgres",
                                                             marks=pytest.mark.postgres)])
def test_states_are_stored_at_a_bounded_rate_and_the_latest_on_a_stop(backend, tmp_path,
                                                                      shots):
    def run(url: str) -> None:
        settings = service_settings(tmp_path / "data", url, checkpoint_interval_s=3600)
        with TestClient(create_app(settings)) as c:
            r = c.post("/v1/sessions", headers=ADMIN, json={
                "map_id": build_map(c, shots[0][:6]), "params": FAST, "seed": 3})
            sid, auth = r.json()["id"], {"Authorization": f"Bearer {r.json()['token']}"}
            for q in shots[1][:6]:
                assert post_frame(c, sid, q.jpeg, auth, wait="true").status_code == 200
            # the first state was stored; the five after it wait in memory
            assert _state(c, sid) == (0, 6)
        with TestClient(create_app(settings)) as c:
            # the stop stored the latest
            assert _state(c, sid) == (5, 6)
            r = post_frame(c, sid, shots[1][6].jpeg, auth, wait="true")
            assert r.status_code == 200 and r.json()["seq"] == 6
            read = c.get(f"/v1/sessions/{sid}", headers=auth).json()
            assert (read["frames_processed"], read["frames_failed"]) == (7, 0)
            assert len(c.get(f"/v1/sessions/{sid}/poses", headers=auth).json()) == 7

    if backend == "sqlite":
        run(f"sqlite:///{tmp_path / 'vloc.sqlite3'}")
    else:
        with postgres_schema_url() as url:
            run(url)
