"""Two API processes (``vloc serve``) on different ports sharing PostgreSQL, Redis and a real
local Ray cluster: frames of one session alternated between them, its poses on a WebSocket
held by the other, its shard killed mid-stream, one of the processes killed."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import signal
import time
import uuid
from collections.abc import AsyncIterator, Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
from websockets.asyncio.client import ClientConnection, connect

from tests.app.imagery import map_and_queries
from tests.conftest import REDIS_URL, postgres_schema_url, require_redis
from tests.e2e.conftest import Server, start_server
from tests.e2e.test_server import _build, _build_map

pytestmark = [pytest.mark.postgres, pytest.mark.redis]

ray = pytest.importorskip("ray")

from vloc.workers.engine.ray_engine import shard_name, shard_of  # noqa: E402

ADMIN_KEY = "replica-test-admin-key-0123456789"
N_SHARDS = 2
ENV: dict[str, str] = {}


@pytest.fixture(scope="module")
def replicas(ray_cluster, tmp_path_factory) -> Iterator[tuple[Server, Server, str]]:
    """Replicas a and b, and the Ray namespace of their shards (their environment and data
    directory in ``ENV``)."""
    require_redis()
    namespace = f"vloc-e2e-{uuid.uuid4().hex[:8]}"
    data_dir = tmp_path_factory.mktemp("replicas") / "data"
    with postgres_schema_url() as database_url:
        env = {"VLOC_ENGINE": "ray", "VLOC_RAY_ADDRESS": ray_cluster,
               "VLOC_RAY_SHARDS": str(N_SHARDS), "VLOC_RAY_SHARD_CPUS": "0.25",
               "VLOC_RAY_NAMESPACE": namespace, "VLOC_DATABASE_URL": database_url,
               "VLOC_REDIS_URL": REDIS_URL, "VLOC_ADMIN_KEY": ADMIN_KEY}
        ENV.update(env, data_dir=str(data_dir))
        servers = []
        try:
            for name in ("a", "b"):
                servers.append(start_server(data_dir, env={**env, "VLOC_INSTANCE_NAME": name}))
            yield servers[0], servers[1], namespace
        finally:
            for srv in servers:
                if srv.process.poll() is None:
                    srv.process.kill()
                    srv.process.wait(10)
            for name in [*(shard_name(i) for i in range(N_SHARDS)), "vloc-maps"]:
                with contextlib.suppress(ValueError):  # never started
                    ray.kill(ray.get_actor(name, namespace=namespace))


@pytest.fixture(scope="module")
def shots():
    return map_and_queries(10)


@pytest.fixture(scope="module")
def session(replicas, shots) -> dict:
    """A map built through replica a and a session on it, opened through a."""
    a, _, _ = replicas
    maps, _ = shots

    async def make():
        async with httpx.AsyncClient(base_url=a.base_url, headers=_admin(), timeout=120) as h:
            map_id = await _build_map(h, maps)
            r = await h.post("/v1/sessions", json={
                "map_id": map_id, "mode": "hybrid", "params": {"n_particles": 100}, "seed": 4})
            assert r.status_code == 201, r.text
            return {"map_id": map_id, "id": r.json()["id"], "token": r.json()["token"]}

    return asyncio.run(make())


def _admin() -> dict:
    return {"Authorization": f"Bearer {ADMIN_KEY}"}


async def _post(http: httpx.AsyncClient, sid: str, token: str, jpeg: bytes) -> httpx.Response:
    return await http.post(f"/v1/sessions/{sid}/frames", content=jpeg, headers={
        "Authorization": f"Bearer {token}", "Content-Type": "image/jpeg"})


@contextlib.asynccontextmanager
async def _stream(server: Server, sid: str, token: str) -> AsyncIterator[ClientConnection]:
    """The session's pose stream on ``server``, past its hello."""
    url = f"{server.ws_url}/v1/sessions/{sid}/stream?token={token}"
    async with connect(url, max_size=2**22) as ws:
        assert json.loads(await ws.recv())["type"] == "hello"
        yield ws


async def _settled(http: httpx.AsyncClient, sid: str, n: int) -> list[dict]:
    """The session's stored outcomes once there are ``n`` of them."""
    for _ in range(600):
        poses = (await http.get(f"/v1/sessions/{sid}/poses", headers=_admin())).json()
        if len(poses) >= n:
            return poses
        await asyncio.sleep(0.1)
    raise AssertionError(f"only {len(poses)} of {n} outcomes stored")


def test_frames_alternated_between_replicas_keep_their_order_and_stream_on_the_other(
        replicas, session, shots):
    a, b, _ = replicas
    _, queries = shots
    sid, token = session["id"], session["token"]

    async def scenario():
        async with httpx.AsyncClient(base_url=a.base_url, timeout=120) as ha, \
                httpx.AsyncClient(base_url=b.base_url, timeout=120) as hb:
            # The stream is held by b, which has not seen the session yet.
            async with _stream(b, sid, token) as ws:
                seqs = []
                for i, q in enumerate(queries[:6]):
                    r = await _post(ha if i % 2 == 0 else hb, sid, token, q.jpeg)
                    assert r.status_code == 202, r.text
                    seqs.append(r.json()["seq"])
                # Two at once, one through each replica: distinct numbers, both answered.
                both = await asyncio.gather(_post(ha, sid, token, queries[6].jpeg),
                                            _post(hb, sid, token, queries[7].jpeg))
                assert [r.status_code for r in both] == [202, 202]
                pair = sorted(r.json()["seq"] for r in both)
                got = [json.loads(await asyncio.wait_for(ws.recv(), 120)) for _ in range(8)]
            poses = await _settled(hb, sid, 8)
            read = (await ha.get(f"/v1/sessions/{sid}", headers=_admin())).json()
        return seqs, pair, got, poses, read

    seqs, pair, got, poses, read = asyncio.run(scenario())
    assert seqs == list(range(6)) and pair == [6, 7]
    # Every pose reached the stream on b, in seq order, whichever replica took the frame.
    assert [m["seq"] for m in got] == list(range(8))
    assert all(m["type"] == "pose" for m in got)
    assert [(p["type"], p["seq"]) for p in poses] == [("pose", s) for s in range(8)]
    assert (read["last_seq"], read["frames_processed"], read["frames_failed"]) == (7, 8, 0)


def test_a_session_follows_its_map_to_a_revision_restored_through_the_other_replica(
        replicas, shots):
    """The map restored to its first revision through a, while its session streams on b
    and takes frames from both: the session moves between two frames (through a at once,
    through b when b next reads the map's revision), with no frame lost, its frames in
    order, and each pose naming the revision it was made on, streamed and stored alike."""
    a, b, _ = replicas
    maps, queries = shots

    async def post(http: httpx.AsyncClient, sid: str, token: str, jpeg: bytes) -> dict:
        r = await http.post(f"/v1/sessions/{sid}/frames?wait=true", content=jpeg,
                            headers={"Authorization": f"Bearer {token}",
                                     "Content-Type": "image/jpeg"})
        assert r.status_code == 200 and r.json()["type"] == "pose", r.text
        return r.json()

    async def scenario():
        async with httpx.AsyncClient(base_url=a.base_url, headers=_admin(), timeout=120) \
                as ha, httpx.AsyncClient(base_url=b.base_url, timeout=120) as hb:
            map_id = await _build_map(ha, maps[:7])
            files = [("files", (s.name, s.jpeg, "image/jpeg")) for s in maps[7:]]
            assert (await ha.post(f"/v1/maps/{map_id}/images", files=files)).status_code == 201
            assert (await _build(ha, map_id))["revision"] == 2
            r = await hb.post("/v1/sessions", headers=_admin(), json={
                "map_id": map_id, "mode": "hybrid", "params": {"n_particles": 100},
                "seed": 6})
            assert r.status_code == 201 and r.json()["follows_map"], r.text
            sid, token = r.json()["id"], r.json()["token"]
            answers = []
            async with _stream(b, sid, token) as ws:
                for i in range(4):
                    answers.append(await post(ha if i % 2 else hb, sid, token,
                                              queries[i].jpeg))
                r = await ha.post(f"/v1/maps/{map_id}/revisions/1/restore")
                assert r.status_code == 200, r.text
                for i in range(4, 9):  # through a first, which moves the session at once
                    answers.append(await post(hb if i % 2 else ha, sid, token,
                                              queries[i].jpeg))
                streamed = [json.loads(await asyncio.wait_for(ws.recv(), 60))
                            for _ in range(9)]
            stored = await _settled(hb, sid, 9)
            read = (await hb.get(f"/v1/sessions/{sid}", headers=_admin())).json()
        return answers, streamed, stored, read

    answers, streamed, stored, read = asyncio.run(scenario())
    revisions = [p["map_revision"] for p in answers]
    assert revisions == [2] * 4 + [1] * 5
    assert [(m["seq"], m["map_revision"]) for m in streamed] == \
        [(p["seq"], p["map_revision"]) for p in stored] == list(enumerate(revisions))
    assert (read["map_revision"], read["frames_processed"], read["frames_failed"]) == (1, 9, 0)


def test_a_killed_shard_resumes_the_session_and_every_frame_is_answered_or_reported(
        replicas, session, shots):
    a, b, namespace = replicas
    _, queries = shots
    sid, token = session["id"], session["token"]
    shard = ray.get_actor(shard_name(shard_of(sid, N_SHARDS)), namespace=namespace)
    pid, _, _ = ray.get(shard.ping.remote())

    async def scenario():
        async with httpx.AsyncClient(base_url=a.base_url, timeout=120) as ha, \
                httpx.AsyncClient(base_url=b.base_url, timeout=120) as hb:
            before = len(await _settled(ha, sid, 0))
            accepted = []
            for i, q in enumerate(queries[:8]):
                if i == 3:
                    os.kill(pid, signal.SIGKILL)  # frames 0-2 of this burst in flight or done
                for _ in range(50):
                    r = await _post(ha if i % 2 == 0 else hb, sid, token, q.jpeg)
                    if r.status_code != 503:  # the shard restarting: retry, as a client would
                        break
                    await asyncio.sleep(0.2)
                assert r.status_code == 202, r.text
                accepted.append(r.json()["seq"])
            poses = await _settled(hb, sid, before + len(accepted))
            read = (await ha.get(f"/v1/sessions/{sid}", headers=_admin())).json()
        return before, accepted, poses, read

    before, accepted, poses, read = asyncio.run(scenario())
    assert accepted == list(range(before, before + 8))
    outcomes = {p["seq"]: p for p in poses}
    # Nothing lost: every accepted frame has its pose or its error.
    assert set(accepted) <= set(outcomes)
    failed = [s for s in accepted if outcomes[s]["type"] == "frame_error"]
    assert all(outcomes[s]["kind"] == "worker_died" for s in failed)
    assert all(s < accepted[3] + 1 for s in failed)  # only frames sent before the kill
    # After the kill the session goes on from its checkpoint.
    assert [outcomes[s]["type"] for s in accepted[4:]] == ["pose"] * 4
    assert read["frames_processed"] + read["frames_failed"] == before + 8
    assert ray.get(shard.ping.remote())[0] != pid


def test_frames_a_dead_replica_left_queued_are_settled_by_a_live_one(replicas, session):
    """A replica that died after recording a frame and before answering it: any live
    replica reports the frame (failed, interrupted) on the session's stream, in its poses
    and in its counters, without waiting for the dead one to start again."""
    from sqlalchemy import create_engine, text

    _, b, _ = replicas
    sid, token = session["id"], session["token"]
    db = create_engine(ENV["VLOC_DATABASE_URL"])

    async def scenario():
        async with httpx.AsyncClient(base_url=b.base_url, timeout=60) as hb:
            read = (await hb.get(f"/v1/sessions/{sid}", headers=_admin())).json()
            seq = read["last_seq"] + 1_000
            async with _stream(b, sid, token) as ws:
                with db.begin() as conn:  # what a replica named "gone" left behind
                    conn.execute(text(
                        "INSERT INTO frames (session_id, seq, received_at, status, owner) "
                        "VALUES (:sid, :seq, now(), 'queued', 'gone')"),
                        {"sid": uuid.UUID(sid), "seq": seq})
                message = json.loads(await asyncio.wait_for(ws.recv(), 30))
            after = (await hb.get(f"/v1/sessions/{sid}", headers=_admin())).json()
            poses = (await hb.get(f"/v1/sessions/{sid}/poses", headers=_admin(),
                                  params={"after_seq": seq - 1})).json()
        return seq, read, message, after, poses

    try:
        seq, read, message, after, poses = asyncio.run(scenario())
    finally:
        db.dispose()
    assert (message["type"], message["seq"], message["kind"]) == ("frame_error", seq,
                                                                  "interrupted")
    assert [(p["type"], p["seq"], p["kind"]) for p in poses] == [
        ("frame_error", seq, "interrupted")]
    assert after["frames_failed"] == read["frames_failed"] + 1
    assert after["frames_processed"] == read["frames_processed"]
    assert after["last_seq"] == seq


def test_a_replica_killed_with_a_seq_reserved_stalls_the_other_for_under_a_second(
        replicas, session, shots):
    """Replica a reserves a frame's seq in the shard and dies before sending the frame
    (its record is held up in the database): the frames b takes next wait only until a's
    lease lapses, not VLOC_RAY_HOLD_S, and b refuses none of them."""
    from sqlalchemy import create_engine, text

    a, b, _ = replicas
    _, queries = shots
    sid, token = session["id"], session["token"]
    db = create_engine(ENV["VLOC_DATABASE_URL"])

    async def blocked_writers() -> int:
        with db.connect() as conn:
            return conn.scalar(text("SELECT count(*) FROM pg_stat_activity "
                                    "WHERE wait_event_type = 'Lock'"))

    async def scenario():
        async with httpx.AsyncClient(base_url=a.base_url, timeout=60) as ha, \
                httpx.AsyncClient(base_url=b.base_url, timeout=60) as hb, \
                _stream(b, sid, token) as ws:
            lock = db.connect()
            tx = lock.begin()
            lock.execute(text("LOCK TABLE frames IN EXCLUSIVE MODE"))
            posted_to_a = asyncio.create_task(_post(ha, sid, token, queries[0].jpeg))
            for _ in range(300):  # until a has its seq and waits to record the frame
                if await blocked_writers():
                    break
                await asyncio.sleep(0.05)
            else:
                raise AssertionError("replica a never reached the database")
            a.process.send_signal(signal.SIGKILL)
            a.process.wait(10)
            tx.rollback()
            lock.close()
            released = time.monotonic()
            with contextlib.suppress(httpx.TransportError):
                await posted_to_a
            codes, arrivals, seqs = [], [], []

            async def listen():
                while len(arrivals) < 15:
                    msg = json.loads(await asyncio.wait_for(ws.recv(), 60))
                    arrivals.append(time.monotonic())
                    seqs.append(msg["seq"])

            listener = asyncio.create_task(listen())
            for i in range(15):  # 5 frames a second for 3 s
                r = await _post(hb, sid, token, queries[1 + i % 8].jpeg)
                codes.append(r.status_code)
                await asyncio.sleep(0.2)
            await listener
        return released, codes, arrivals, seqs

    try:
        released, codes, arrivals, seqs = asyncio.run(scenario())
    finally:
        db.dispose()
    gaps = np.diff([released, *arrivals])
    assert codes == [202] * 15
    assert seqs == sorted(seqs)
    assert gaps.max() <= 1.5, gaps


def test_killing_one_replica_leaves_the_other_serving_every_session(replicas, session, shots):
    a, b, _ = replicas
    _, queries = shots
    sid, token = session["id"], session["token"]
    a.process.send_signal(signal.SIGKILL)
    a.process.wait(10)

    async def scenario():
        async with httpx.AsyncClient(base_url=b.base_url, timeout=120) as hb:
            assert (await hb.get("/readyz")).status_code == 200
            before = await _settled(hb, sid, 0)
            r = await hb.post(f"/v1/sessions/{sid}/frames?wait=true", content=queries[0].jpeg,
                              headers={"Authorization": f"Bearer {token}",
                                       "Content-Type": "image/jpeg"})
            # A second session, opened on b, on the map built through a.
            r2 = await hb.post("/v1/sessions", headers=_admin(), json={
                "map_id": session["map_id"], "mode": "hybrid",
                "params": {"n_particles": 100}, "seed": 5})
            other = r2.json()
            r3 = await hb.post(f"/v1/sessions/{other['id']}/frames?wait=true",
                               content=queries[1].jpeg,
                               headers={"Authorization": f"Bearer {other['token']}",
                                        "Content-Type": "image/jpeg"})
        return before, r, r2, r3

    before, r, r2, r3 = asyncio.run(scenario())
    # The next seq follows the last frame stepped. Counting the stored outcomes would not
    # give it: the earlier tests stored a made-up frame far ahead, and whether the frame a
    # reserved before it was killed reached the database (its insert was waiting on a lock)
    # is a race that the kill decides.
    stepped = max(p["seq"] for p in before if p["type"] == "pose")
    assert r.status_code == 200 and r.json()["type"] == "pose", r.text
    assert r.json()["seq"] == stepped + 1
    assert r.json()["seq"] not in {p["seq"] for p in before}
    assert r2.status_code == 201, r2.text
    assert r3.status_code == 200 and r3.json()["seq"] == 0



def test_serve_processes_runs_api_processes_on_one_port_and_replaces_one_that_dies(
        replicas, session, shots):
    from tests.procs import children, cmdline, running, wait_gone

    def api_processes() -> set[int]:
        # multiprocessing's resource tracker is a child of the supervisor too.
        return {p for p in children(server.process.pid)
                if running(p) and "resource_tracker" not in cmdline(p)}

    _, queries = shots
    env = {k: v for k, v in ENV.items() if k != "data_dir"}
    server = start_server(Path(ENV["data_dir"]), env={**env, "VLOC_INSTANCE_NAME": "multi"},
                          args=("--processes", "2"))
    try:
        procs = api_processes()
        assert len(procs) == 2
        sid, token = session["id"], session["token"]
        headers = {"Authorization": f"Bearer {token}", "Content-Type": "image/jpeg"}

        def frame(i: int) -> httpx.Response:
            # A connection of its own each time: the kernel spreads them over the processes.
            for _ in range(50):
                try:
                    return httpx.post(f"{server.base_url}/v1/sessions/{sid}/frames?wait=true",
                                      content=queries[i % len(queries)].jpeg, headers=headers,
                                      timeout=60)
                except httpx.TransportError:
                    time.sleep(0.2)
            raise AssertionError("no API process answered")

        first = [frame(i) for i in range(4)]
        assert [r.status_code for r in first] == [200] * 4
        seqs = [r.json()["seq"] for r in first]
        assert seqs == list(range(seqs[0], seqs[0] + 4))
        victim = min(procs)
        os.kill(victim, signal.SIGKILL)
        assert not wait_gone({victim})
        after = [frame(i) for i in range(4)]
        assert [r.status_code for r in after] == [200] * 4
        assert [r.json()["seq"] for r in after] == list(range(seqs[-1] + 1, seqs[-1] + 5))
        # The supervisor started another process in the dead one's place.
        deadline = time.monotonic() + 60
        while len(api_processes()) < 2 and time.monotonic() < deadline:
            time.sleep(0.2)
        now = api_processes()
        assert len(now) == 2 and victim not in now
    finally:
        assert server.stop() in (0, -15)
