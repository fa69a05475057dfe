"""The real server stopped the hard way (SIGKILL) and the graceful way (SIGTERM) with frames
queued: every accepted frame is answered or reported, no seq is reused, no process of the
server outlives it, and the streams end with 1001 after their last pose."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import signal
from collections.abc import Awaitable, Callable
from dataclasses import dataclass

import httpx
import pytest
from sqlalchemy import create_engine, text
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed

from tests.app.imagery import map_and_queries
from tests.conftest import postgres_schema_url
from tests.e2e.conftest import Server, start_server
from tests.e2e.test_server import _build_map
from tests.procs import descendants, pool_workers, wait_gone

QUEUED = 25


@pytest.fixture(params=["sqlite", pytest.param("postgres", marks=pytest.mark.postgres)])
def database_env(request) -> dict:
    """Server environment: the embedded SQLite file, or a fresh PostgreSQL schema."""
    if request.param == "sqlite":
        yield {}
        return
    with postgres_schema_url() as url:
        yield {"VLOC_DATABASE_URL": url}


async def _session(http: httpx.AsyncClient, map_id: str) -> tuple[str, str]:
    r = await http.post("/v1/sessions", json={
        "map_id": map_id, "mode": "hybrid", "params": {"n_particles": 100}, "seed": 4})
    assert r.status_code == 201, r.text
    return r.json()["id"], r.json()["token"]


async def _post(http, sid, token, data, **params) -> httpx.Response:
    return await http.post(f"/v1/sessions/{sid}/frames", content=data, params=params,
                           headers={"Authorization": f"Bearer {token}",
                                    "Content-Type": "image/jpeg"})


def _signal_all(pids, sig) -> None:
    for pid in pids:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, sig)


def test_killed_server_reports_every_accepted_frame_and_never_reuses_a_seq(
        tmp_path, database_env):
    maps, queries = map_and_queries(10)
    data_dir = tmp_path / "data"
    server = start_server(data_dir, workers=1, env=database_env)
    admin = {"Authorization": f"Bearer {server.admin_key()}"}

    async def before_the_kill() -> tuple[str, str, list[int]]:
        async with httpx.AsyncClient(base_url=server.base_url, headers=admin,
                                     timeout=60) as http:
            sid, token = await _session(http, await _build_map(http, maps))
            for q in queries[:2]:
                assert (await _post(http, sid, token, q.jpeg, wait="true")).status_code == 200
            # The worker runs nothing from here on: the frames accepted next stay queued.
            _signal_all(pool_workers(server.process.pid), signal.SIGSTOP)
            accepted = []
            for i in range(QUEUED):
                r = await _post(http, sid, token, queries[i % len(queries)].jpeg)
                assert r.status_code == 202, r.text
                accepted.append(r.json()["seq"])
        return sid, token, accepted

    try:
        sid, token, accepted = asyncio.run(before_the_kill())
    finally:
        below = descendants(server.process.pid)
        server.process.kill()
        server.process.wait(30)
        _signal_all(below, signal.SIGCONT)
    # Workers, forkserver and resource tracker go with the server, including the worker
    # that finds a task half written into its queue.
    assert wait_gone(below) == set()
    assert accepted == list(range(2, 2 + QUEUED))

    server = start_server(data_dir, workers=1, env=database_env)
    bearer = {"Authorization": f"Bearer {token}"}

    async def after_the_restart():
        async with httpx.AsyncClient(base_url=server.base_url, headers=bearer,
                                     timeout=60) as http:
            listed = (await http.get(f"/v1/sessions/{sid}/poses")).json()
            url = f"{server.ws_url}/v1/sessions/{sid}/stream?token={token}"
            async with connect(url) as ws:
                hello = json.loads(await ws.recv())
                reported = [json.loads(await asyncio.wait_for(ws.recv(), 60))
                            for _ in range(QUEUED)]
                r = await _post(http, sid, token, queries[0].jpeg, wait="true")
            session = (await http.get(f"/v1/sessions/{sid}")).json()
        return listed, hello, reported, r, session

    try:
        listed, hello, reported, r, session = asyncio.run(after_the_restart())
    finally:
        server.stop()
    # Every accepted frame is there once: answered before the kill, or reported.
    assert [m["seq"] for m in listed] == list(range(2 + QUEUED))
    assert [m["type"] for m in listed[:2]] == ["pose", "pose"]
    assert {(m["type"], m["kind"]) for m in listed[2:]} == {("frame_error", "interrupted")}
    assert hello["last_seq"] == 1 + QUEUED
    assert [(m["type"], m["seq"], m["kind"]) for m in reported] == [
        ("frame_error", seq, "interrupted") for seq in accepted]
    # The next frame continues after the last accepted seq.
    assert r.status_code == 200 and r.json()["seq"] == 2 + QUEUED
    assert (session["frames_processed"], session["frames_failed"]) == (3, QUEUED)


@dataclass
class Drain:
    """A SIGTERM with frames queued as a client saw it: the seqs its frames were given,
    the messages streamed to it, the stream's close code and the seconds from the SIGTERM
    to that close; and the server's exit status."""
    server: Server
    sid: str
    accepted: list[int]
    streamed: list[dict]
    close_code: int | None
    took: float
    returncode: int


HoldWorkers = Callable[[ClientConnection, set[int]], Awaitable[list[dict]]]


def _sigterm_with_frames_queued(tmp_path, n_images: int, hold: HoldWorkers | None = None,
                                ) -> Drain:
    """A one-worker server, a session with its stream open and its worker stopped, a frame
    queued per query image, then SIGTERM. ``hold(ws, workers)`` runs right after the SIGTERM
    with the workers stopped and returns the messages it read; then the workers go on and
    the stream is read to its close."""
    maps, queries = map_and_queries(n_images)
    server = start_server(tmp_path / "data", workers=1)
    admin = {"Authorization": f"Bearer {server.admin_key()}"}

    async def scenario() -> tuple[str, list[int], list[dict], int | None, float]:
        async with httpx.AsyncClient(base_url=server.base_url, headers=admin,
                                     timeout=60) as http:
            sid, token = await _session(http, await _build_map(http, maps))
            url = f"{server.ws_url}/v1/sessions/{sid}/stream?token={token}"
            async with connect(url) as ws:
                assert json.loads(await ws.recv())["type"] == "hello"
                workers = pool_workers(server.process.pid)
                _signal_all(workers, signal.SIGSTOP)
                try:
                    accepted = [(await _post(http, sid, token, q.jpeg)).json()["seq"]
                                for q in queries]
                    server.process.send_signal(signal.SIGTERM)
                    stopped = asyncio.get_running_loop().time()
                    got = await hold(ws, workers) if hold else []
                finally:
                    _signal_all(workers, signal.SIGCONT)
                with contextlib.suppress(ConnectionClosed):
                    async for raw in ws:
                        got.append(json.loads(raw))
                took = asyncio.get_running_loop().time() - stopped
                return sid, accepted, got, ws.close_code, took

    try:
        outcome = asyncio.run(scenario())
        returncode = server.process.wait(60)
    finally:
        if server.process.poll() is None:
            server.process.kill()
    return Drain(server, *outcome, returncode)


def test_sigterm_answers_queued_frames_streams_them_then_closes_with_1001(tmp_path):
    drain = _sigterm_with_frames_queued(tmp_path, 10)
    server, sid, accepted = drain.server, drain.sid, drain.accepted
    assert drain.returncode in (0, -signal.SIGTERM)
    assert accepted == list(range(len(accepted)))
    assert [(m["type"], m["seq"]) for m in drain.streamed] == [("pose", s) for s in accepted]
    assert drain.close_code == 1001
    log = server.stderr_path.read_text()
    assert '"msg": "vloc stopped"' in log and "Traceback" not in log
    db = create_engine(f"sqlite:///{server.data_dir / 'vloc.sqlite3'}")
    with db.connect() as conn:
        stored = conn.execute(text("SELECT seq FROM pose_estimates WHERE session_id = :s "
                                   "ORDER BY seq"), {"s": sid.replace("-", "")}).scalars()
        assert list(stored) == accepted
    db.dispose()


def test_a_drain_longer_than_ten_seconds_answers_every_frame_while_the_backlog_shrinks(
        tmp_path):
    """The drain follows the backlog: its workers are held for 6 s twice, with one frame
    answered in between, and every frame is still streamed before 1001."""

    async def hold(ws: ClientConnection, workers: set[int]) -> list[dict]:
        await asyncio.sleep(6)  # a slow backlog: nothing answered for 6 s
        _signal_all(workers, signal.SIGCONT)
        got = [json.loads(await asyncio.wait_for(ws.recv(), 30))]
        _signal_all(workers, signal.SIGSTOP)
        await asyncio.sleep(6)  # and 6 s more
        return got

    drain = _sigterm_with_frames_queued(tmp_path, 6, hold)
    assert drain.returncode in (0, -signal.SIGTERM)
    assert [(m["type"], m["seq"]) for m in drain.streamed] == [("pose", s)
                                                               for s in drain.accepted]
    assert drain.close_code == 1001 and drain.took > 12
