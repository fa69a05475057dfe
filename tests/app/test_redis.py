"""Pose fan-out through the real Redis, for several API replicas."""

from __future__ import annotations

import asyncio
import uuid

import pytest
from fastapi.testclient import TestClient

from tests.app.conftest import ADMIN, FAST, build_map, service_settings
from tests.app.test_sessions import open_stream, post_frame
from vloc.app.main import create_app
from vloc.app.sessions.schemas import FrameError
from vloc.app.stream.hub import Encoded
from vloc.app.stream.redis_hub import RedisHub

pytestmark = pytest.mark.redis


def test_messages_reach_the_subscribers_of_another_replica_in_order(redis_url):
    session = uuid.uuid4().hex

    async def scenario():
        a, b = RedisHub(redis_url), RedisHub(redis_url)
        await a.start()
        await b.start()
        try:
            on_b, on_a = b.subscribe(session), a.subscribe(session)
            elsewhere = b.subscribe(uuid.uuid4().hex)
            await b.ready(session)
            await a.ready(session)
            for i in range(50):
                a.publish(session, {"type": "pose", "seq": i})
            a.publish(session, written)
            got_b = [await asyncio.wait_for(on_b.queue.get(), 5) for _ in range(51)]
            got_a = [await asyncio.wait_for(on_a.queue.get(), 5) for _ in range(51)]
            b.unsubscribe(on_b)
            a.close_session(session)
            closed = await asyncio.wait_for(on_a.queue.get(), 5)
            return got_b, got_a, elsewhere.queue.qsize(), closed
        finally:
            await a.stop()
            await b.stop()

    # a frame's message, written once: the other replica sends the text it received
    written = Encoded.of(FrameError(session_id=uuid.uuid4(), seq=50, captured_at=None,
                                    kind="error", reason="r\u00e9ason", latency_ms=2.5))
    got_b, got_a, stray, closed = asyncio.run(scenario())
    assert [m["seq"] for m in got_b] == list(range(51)) == [m["seq"] for m in got_a]
    assert isinstance(got_b[-1], Encoded) and got_b[-1].text == written.text
    assert stray == 0 and closed["type"] == "closed"


def test_app_streams_poses_through_redis(tmp_path, redis_url, shots):
    settings = service_settings(tmp_path / "data", f"sqlite:///{tmp_path}/v.db",
                                redis_url=redis_url)
    with TestClient(create_app(settings)) as c:
        map_id = build_map(c, shots[0][:5])
        r = c.post("/v1/sessions", headers=ADMIN,
                   json={"map_id": map_id, "params": FAST, "seed": 2})
        sid, auth = r.json()["id"], {"Authorization": f"Bearer {r.json()['token']}"}
        with open_stream(c, sid, auth) as ws:
            assert ws.receive_json()["type"] == "hello"
            for q in shots[1][:3]:
                assert post_frame(c, sid, q.jpeg, auth).status_code == 202
            assert [ws.receive_json()["seq"] for _ in range(3)] == [0, 1, 2]
