"""The Python client against the real app in process: every route, every error class.

HTTP goes through Starlette's TestClient (sync) or ``httpx.ASGITransport`` (async), the pose
stream through the TestClient's WebSocket or, for the ``websockets`` code path, through a
real socket to uvicorn. Retry and error-mapping rules are checked on ``httpx.MockTransport``,
where the answers can be scripted.
"""

from __future__ import annotations

import contextlib
import json

import httpx
import numpy as np
import pytest

import vloc.clients as clients
from tests.clients.conftest import ADMIN_KEY, FAST
from vloc.clients.demo import free_port
from vloc.clients.sdk import (
    APIError,
    AsyncClient,
    BadRequest,
    Client,
    Conflict,
    Forbidden,
    FrameAccepted,
    FrameError,
    FrameRejected,
    JobFailed,
    NotFound,
    PayloadTooLarge,
    Pose,
    RetryPolicy,
    ServerError,
    Session,
    SessionDeleted,
    TooManyRequests,
    TransportError,
    Unauthorized,
    UnprocessableEntity,
    UnsupportedMediaType,
    VlocError,
    WaitTimeout,
)
from vloc.clients.sdk._exceptions import error_class, error_for_response
from vloc.clients.sdk.testing import in_process_client

# -- fixtures --------------------------------------------------------------------------------


@pytest.fixture
def session(vloc, built_map) -> Session:
    s = vloc.create_session(built_map, mode="hybrid", params=FAST, seed=3)
    yield s
    with contextlib.suppress(NotFound):
        vloc.delete_session(s)


def anonymous(app_client) -> Client:
    """A client without any credentials."""
    return in_process_client(app_client, admin_key="", retry=0)


# -- maps, images, builds --------------------------------------------------------------------


def test_map_create_list_get_delete(vloc):
    m = vloc.create_map("campus")
    assert (m.name, m.status, m.revision, m.image_count) == ("campus", "empty", 0, 0)
    assert m.id in {x.id for x in vloc.list_maps()}
    assert vloc.get_map(m.id) == m
    assert vloc.delete_map(m.id) is None
    with pytest.raises(NotFound) as info:
        vloc.get_map(m.id)
    err = info.value
    assert (err.status, err.kind, err.title) == (404, "not-found", "Not Found")
    assert err.instance == f"/v1/maps/{m.id}" and m.id in err.detail


def test_upload_reports_each_file(vloc, shots, app_client):
    from tests.app.imagery import plain_jpeg

    maps, _ = shots
    m = vloc.create_map("upload")
    result = vloc.upload_images(m.id, [(s.name, s.jpeg) for s in maps[:3]]
                                + [("nogps.jpg", plain_jpeg())])
    assert [a.filename for a in result.accepted] == [s.name for s in maps[:3]]
    assert [(r.filename, r.status, r.reason) for r in result.rejected] == \
        [("nogps.jpg", 422, "no-gps")]
    assert result.accepted[0].lat == pytest.approx(maps[0].lat, abs=1e-6)
    assert [i.filename for i in vloc.list_images(m.id)] == [s.name for s in maps[:3]]
    # One file without EXIF, positioned by the form fields.
    one = vloc.upload_images(m.id, [("placed.jpg", plain_jpeg(90))], lat=41.0, lon=-83.0)
    assert one.accepted[0].position_source == "form"
    assert (one.accepted[0].lat, one.accepted[0].lon) == (41.0, -83.0)
    assert vloc.get_map(m.id).image_count == 4


def test_upload_from_paths(vloc, dataset_dir):
    m = vloc.create_map("paths")
    paths = sorted((dataset_dir / "images").glob("map_00[0-2].jpg"))
    result = vloc.upload_images(m.id, paths)
    assert [a.filename for a in result.accepted] == [p.name for p in paths]
    assert result.accepted[0].content_type == "image/jpeg"


def test_upload_errors(vloc, shots):
    from tests.app.imagery import plain_jpeg, png_bomb

    maps, _ = shots
    m = vloc.create_map("bad uploads")
    with pytest.raises(UnprocessableEntity) as info:
        vloc.upload_images(m.id, [("a.jpg", plain_jpeg())])
    assert info.value.kind == "no-image-accepted"
    assert info.value.body["rejected"][0]["reason"] == "no-gps"
    with pytest.raises(PayloadTooLarge):
        vloc.upload_images(m.id, [("bomb.png", png_bomb())], lat=41.0, lon=-83.0)
    with pytest.raises(UnprocessableEntity) as info:
        vloc.upload_images(m.id, [("x.jpg", maps[0].jpeg)], lat=95.0, lon=0.0)
    assert info.value.kind == "validation" and "lat" in info.value.body["detail"]
    vloc.upload_images(m.id, [("a.jpg", maps[0].jpeg)])
    with pytest.raises(Conflict) as info:
        vloc.upload_images(m.id, [("again.jpg", maps[0].jpeg)])
    assert info.value.body["rejected"][0]["reason"] == "duplicate"
    with pytest.raises(NotFound):
        vloc.upload_images("no-such-map", [("a.jpg", maps[1].jpeg)])


def test_build_progress_and_job(vloc, shots):
    maps, _ = shots
    m = vloc.create_map("build")
    vloc.upload_images(m.id, [(s.name, s.jpeg) for s in maps[:4]])
    assert vloc.get_map(m.id).pending_images == 4
    job = vloc.build_map(m.id)
    assert job.status in ("queued", "running") and job.map_id == m.id
    seen = []
    done = vloc.wait_for_job(job.id, timeout=120, poll_interval=0.05, on_progress=seen.append)
    assert (done.status, done.progress, done.n_images, done.n_extracted, done.revision,
            done.full) == ("done", 1.0, 4, 4, 1, False)
    assert seen[-1] == done
    progress = [j.progress for j in seen]
    assert progress == sorted(progress)
    assert vloc.get_job(job.id) == done
    built = vloc.get_map(m.id)
    assert (built.status, built.revision, built.pending_images) == ("ready", 1, 0)
    assert built.origin is not None and built.local_extent is not None
    assert built.last_job_id == job.id
    # nothing new: up to date, unless the geometry is asked for whole (full implies force)
    with pytest.raises(Conflict) as info:
        vloc.build_map(m.id)
    assert info.value.kind == "map-up-to-date"
    again = vloc.wait_for_job(vloc.build_map(m.id, full=True).id, timeout=120,
                              poll_interval=0.05)
    assert (again.status, again.revision, again.full) == ("done", 2, True)


def test_build_errors(vloc):
    m = vloc.create_map("empty")
    with pytest.raises(Conflict) as info:
        vloc.build_map(m.id)
    assert info.value.kind == "map-empty"
    with pytest.raises(NotFound):
        vloc.get_job("00000000-0000-0000-0000-000000000000")


def test_wait_for_job_raises_on_failure_and_timeout():
    states = iter(["running", "running", "failed"])

    def handler(request: httpx.Request) -> httpx.Response:
        return httpx.Response(200, json={"id": "j1", "status": next(states),
                                         "progress": 0.5, "error": "disk full"})

    sleeps = []
    vloc = Client("http://x", transport=httpx.MockTransport(handler), sleep=sleeps.append)
    with pytest.raises(JobFailed) as info:
        vloc.wait_for_job("j1", poll_interval=0.25)
    assert info.value.job.error == "disk full" and sleeps == [0.25, 0.25]

    stuck = Client("http://x", transport=httpx.MockTransport(
        lambda r: httpx.Response(200, json={"id": "j2", "status": "running"})),
        sleep=lambda s: None)
    with pytest.raises(WaitTimeout):
        stuck.wait_for_job("j2", timeout=0)


def test_admin_routes_need_the_admin_key(app_client, vloc, session):
    with pytest.raises(Unauthorized) as info:
        anonymous(app_client).list_maps()
    assert info.value.kind == "unauthenticated"
    with pytest.raises(Forbidden):
        in_process_client(app_client, admin_key="not-the-key-at-all").list_maps()
    # A session token opens its session, not the admin routes.
    with pytest.raises(Forbidden):
        in_process_client(app_client, admin_key=session.token).list_maps()


# -- sessions and frames ---------------------------------------------------------------------


def test_session_create_get_list_delete(vloc, app_client, built_map):
    s = vloc.create_session(built_map, mode="global", params=FAST, seed=11)
    assert s.token and (s.mode, s.seed, s.map_id, s.map_revision) == ("global", 11, built_map, 1)
    assert s.params["n_particles"] == 60
    assert s.id in {x.id for x in vloc.list_sessions()}
    # The session's own token is enough; the token is never shown again.
    read = anonymous(app_client).get_session(s)
    assert read.id == s.id and read.token is None
    assert vloc.get_session(s.id).frames_processed == 0
    vloc.delete_session(s)
    with pytest.raises(NotFound):
        vloc.get_session(s.id)


def test_session_errors(vloc, app_client, built_map, session):
    with pytest.raises(Conflict) as info:
        vloc.create_session(vloc.create_map("unbuilt").id)
    assert "built" in info.value.detail
    with pytest.raises(UnprocessableEntity):
        vloc.create_session(built_map, mode="no-such-mode")
    with pytest.raises(UnprocessableEntity) as info:
        vloc.create_session(built_map, params={"n_particles": -5})
    assert info.value.status == 422
    with pytest.raises(NotFound):
        vloc.create_session("00000000-0000-0000-0000-000000000000")
    with pytest.raises(Forbidden):
        anonymous(app_client).get_session(session.id, token="wrong-token")
    with pytest.raises(Unauthorized):
        anonymous(app_client).get_session(session.id)


def test_frames_queue_wait_and_read_back(vloc, session, shots):
    _, queries = shots
    accepted = vloc.send_frame(session, queries[0].jpeg, seq=0,
                               captured_at=queries[0].captured_at)
    assert accepted == FrameAccepted(seq=0)
    pose = vloc.send_frame(session, queries[1].jpeg, seq=1, wait=True,
                           captured_at=queries[1].captured_at.timestamp())
    assert isinstance(pose, Pose) and pose.seq == 1 and pose.session_id == session.id
    assert pose.captured_at == queries[1].captured_at
    assert pose.feature in ("sift", "global") and pose.n_particles == 60
    assert pose.cov[0] == pytest.approx(pose.sigma_x ** 2, rel=1e-6)
    # Without seq the server numbers the frame after the last one.
    auto = vloc.send_frame(session, queries[2].jpeg, wait=True)
    assert auto.seq == 2
    poses = vloc.list_poses(session)
    assert [p.seq for p in poses] == [0, 1, 2]
    assert [p.seq for p in vloc.list_poses(session, after_seq=0, limit=1)] == [1]
    s = vloc.get_session(session)
    assert (s.last_seq, s.frames_processed, s.frames_failed) == (2, 3, 0)
    assert s.last_pose.seq == 2 and s.stats.sift_share is not None


def test_iso_capture_times_and_frame_metadata(vloc, session, shots):
    _, queries = shots
    iso = queries[0].captured_at.isoformat().replace("+00:00", "Z")
    pose = vloc.send_frame(session, queries[0].jpeg, wait=True, captured_at=iso,
                           metadata={"altitude_m": 250.0, "heading_deg": 10.0,
                                     "gps_lat": None})
    assert pose.captured_at == queries[0].captured_at
    assert pose.altitude_m == 250.0 and pose.decode_ms > 0
    assert pose.horizontal_accuracy_m > 0 and pose.map_id == session.map_id
    assert pose.geopose.position.h == 250.0
    with pytest.raises(ValueError, match="ISO 8601"):
        vloc.send_frame(session, queries[1].jpeg, captured_at="yesterday")
    with pytest.raises(ValueError, match="unknown frame metadata"):
        vloc.send_frame(session, queries[1].jpeg, metadata={"heading": 10.0})
    with pytest.raises(UnprocessableEntity) as err:
        vloc.send_frame(session, queries[1].jpeg, metadata={"gps_lat": 41.0})
    assert "gps_lat" in str(err.value)
    assert vloc.get_session(session).last_seq == 0


def test_frame_errors(vloc, app_client, session, shots):
    from tests.app.imagery import png

    _, queries = shots
    vloc.send_frame(session, queries[0].jpeg, seq=5)
    with pytest.raises(Conflict) as info:
        vloc.send_frame(session, queries[1].jpeg, seq=5)
    assert (info.value.kind, info.value.body["last_seq"]) == ("duplicate-seq", 5)
    with pytest.raises(Conflict) as info:
        vloc.send_frame(session, queries[1].jpeg, seq=4)
    assert info.value.kind == "stale-seq"
    with pytest.raises(UnsupportedMediaType):
        vloc.send_frame(session, png(), content_type="image/jpeg")
    with pytest.raises(UnsupportedMediaType):
        vloc.send_frame(session, b"GIF89a....", content_type="image/gif")
    with pytest.raises(UnprocessableEntity) as info:
        vloc.send_frame(session, queries[0].jpeg[:2000], content_type="image/jpeg")
    assert info.value.kind in ("truncated-image", "bad-image")
    with pytest.raises(PayloadTooLarge):
        vloc.send_frame(session, queries[0].jpeg + b"\0" * 500_000)
    with pytest.raises(UnprocessableEntity):
        vloc.send_frame(session, queries[0].jpeg, seq=-1)
    with pytest.raises(Forbidden):
        anonymous(app_client).send_frame(session.id, queries[0].jpeg, token="nope")
    with pytest.raises(NotFound):
        vloc.send_frame("00000000-0000-0000-0000-000000000000", queries[0].jpeg)
    # None of the refused frames took a sequence number.
    assert vloc.send_frame(session, queries[1].jpeg, wait=True).seq == 6


def test_reset_and_initial_pose(vloc, session, shots):
    maps, queries = shots
    assert vloc.reset_session(session).id == session.id
    s = vloc.set_initial_pose(session, lat=maps[2].lat, lon=maps[2].lon, sigma=3.0)
    assert s.id == session.id
    vloc.set_initial_pose(session, x=1.0, y=-2.0)
    pose = vloc.send_frame(session, queries[2].jpeg, seq=0, wait=True)
    assert pose.n_particles == 60
    with pytest.raises(UnprocessableEntity):
        vloc.set_initial_pose(session, lat=1.0, lon=2.0, x=3.0, y=4.0)
    with pytest.raises(UnprocessableEntity):
        vloc.set_initial_pose(session, lat=91.0, lon=0.0)


def test_bad_request_from_a_malformed_header(vloc):
    with pytest.raises(BadRequest) as info:
        vloc.request("POST", "/v1/maps", content=b'{"name": "x"}',
                     headers={"content-length": "-1", "content-type": "application/json"})
    assert info.value.status == 400 and "Content-Length" in info.value.detail


def test_health(vloc):
    assert vloc.health() == {"status": "ok"}
    ready = vloc.ready()
    assert (ready["status"], ready["database"], ready["workers"]) == ("ready", "sqlite", 1)
    assert vloc.wait_ready(timeout=5)["status"] == "ready"


# -- the pose stream -------------------------------------------------------------------------


def test_stream_yields_poses_in_order(vloc, session, shots):
    _, queries = shots
    with vloc.stream(session, timeout=60) as poses:
        assert poses.hello["session_id"] == session.id and poses.hello["last_seq"] is None
        for i, q in enumerate(queries[:4]):
            vloc.send_frame(session, q.jpeg, seq=10 + i, captured_at=q.captured_at)
        got = [next(iter(poses)) for _ in range(4)]
    assert [m.seq for m in got] == [10, 11, 12, 13]
    assert all(isinstance(m, Pose) for m in got)
    # What was streamed is what was stored (a waited-for frame is answered once stored,
    # after the frames before it).
    vloc.send_frame(session, queries[4].jpeg, seq=14, wait=True)
    stored = vloc.list_poses(session)[:4]
    assert [p.seq for p in stored] == [10, 11, 12, 13]
    assert [(p.x, p.y, p.feature) for p in stored] == [(p.x, p.y, p.feature) for p in got]


def test_stream_takes_frames_and_reports_refusals(vloc, session, shots):
    _, queries = shots
    with vloc.stream(session, timeout=60) as poses:
        poses.send_frame(queries[0].jpeg, seq=3, captured_at=queries[0].captured_at)
        first = poses.receive()
        poses.send_frame(b"not an image")
        refused = poses.receive()
        poses.send_frame(queries[1].jpeg, seq=3)
        duplicate = poses.receive()
        poses.ping()
        poses.send_frame(queries[1].jpeg)
        after = poses.receive()
    assert isinstance(first, Pose) and first.seq == 3
    assert first.captured_at == queries[0].captured_at
    assert isinstance(refused, FrameRejected) and isinstance(refused.error, UnprocessableEntity)
    assert isinstance(duplicate.error, Conflict) and duplicate.error.kind == "duplicate-seq"
    assert isinstance(after, Pose) and after.seq == 4


def test_stream_raises_when_the_session_is_deleted(vloc, built_map):
    s = vloc.create_session(built_map, mode="sift", params=FAST)
    with vloc.stream(s, timeout=60) as poses:
        vloc.delete_session(s)
        with pytest.raises(SessionDeleted) as info:
            list(poses)
        assert poses.ended
    assert isinstance(info.value, NotFound) and info.value.kind == "session-deleted"


def test_stream_refusals(vloc, app_client, session):
    with pytest.raises(Unauthorized):
        anonymous(app_client).stream(session.id)
    with pytest.raises(Forbidden):
        anonymous(app_client).stream(session.id, token="wrong")
    with pytest.raises(NotFound):
        vloc.stream("00000000-0000-0000-0000-000000000000")


def test_stream_timeout(vloc, session):
    with vloc.stream(session, timeout=0.2) as poses, pytest.raises(WaitTimeout):
        poses.receive()


def test_frame_error_message_parsed():
    from vloc.clients.sdk._stream import _interpret

    msg = _interpret(json.dumps({"type": "frame_error", "session_id": "s", "seq": 4,
                                 "kind": "bad_image", "reason": "corrupt", "latency_ms": 2.0}))
    assert isinstance(msg, FrameError) and (msg.seq, msg.kind) == (4, "bad_image")


# -- a real socket: uvicorn, httpx and the websockets library --------------------------------


def test_real_sockets_sync(live_server, shots):
    maps, queries = shots
    with Client(live_server, admin_key=ADMIN_KEY) as vloc:
        m = vloc.create_map("live")
        vloc.upload_images(m.id, [(s.name, s.jpeg) for s in maps])
        vloc.wait_for_job(vloc.build_map(m.id).id, timeout=120, poll_interval=0.1)
        s = vloc.create_session(m.id, params=FAST, seed=1)
        with vloc.stream(s, timeout=60) as poses:
            vloc.send_frame(s, queries[0].jpeg, seq=0)
            poses.send_frame(queries[1].jpeg, seq=1)
            got = [poses.receive(), poses.receive()]
        assert [p.seq for p in got] == [0, 1]
        with pytest.raises(Forbidden):
            vloc.stream(s.id, token="wrong")
        vloc.delete_session(s)


@pytest.mark.anyio
async def test_real_sockets_async(live_server, shots):
    maps, queries = shots
    async with AsyncClient(live_server, admin_key=ADMIN_KEY) as vloc:
        m = await vloc.create_map("live async")
        await vloc.upload_images(m.id, [(s.name, s.jpeg) for s in maps])
        job = await vloc.build_map(m.id)
        await vloc.wait_for_job(job.id, timeout=120, poll_interval=0.1)
        s = await vloc.create_session(m.id, params=FAST, seed=1)
        async with await vloc.stream(s, timeout=60) as poses:
            await vloc.send_frame(s, queries[0].jpeg, seq=0)
            await poses.send_frame(queries[1].jpeg, seq=1)
            got = [await poses.receive(), await poses.receive()]
            await vloc.delete_session(s)
            with pytest.raises(SessionDeleted):
                [m async for m in poses]
        assert [p.seq for p in got] == [0, 1]
        with pytest.raises(NotFound):
            await vloc.stream(s.id)


@pytest.mark.anyio
async def test_async_client_in_process(tmp_path, shots):
    """AsyncClient over ``httpx.ASGITransport``, the app's lifespan on the test's loop."""
    from tests.clients.conftest import service_settings
    from vloc.app.main import create_app

    maps, queries = shots
    app = create_app(service_settings(tmp_path / "data"))
    async with app.router.lifespan_context(app):
        transport = httpx.ASGITransport(app=app)
        async with AsyncClient("http://testserver", admin_key=ADMIN_KEY,
                               transport=transport, retry=0) as vloc:
            assert (await vloc.health())["status"] == "ok"
            m = await vloc.create_map("async")
            assert [x.id for x in await vloc.list_maps()] == [m.id]
            up = await vloc.upload_images(m.id, [(s.name, s.jpeg) for s in maps[:5]])
            assert len(up.accepted) == 5
            assert len(await vloc.list_images(m.id)) == 5
            job = await vloc.wait_for_job((await vloc.build_map(m.id)).id, timeout=120,
                                          poll_interval=0.05)
            assert (await vloc.get_job(job.id)).status == "done"
            s = await vloc.create_session(m.id, mode="hybrid", params=FAST, seed=2)
            assert [x.id for x in await vloc.list_sessions()] == [s.id]
            pose = await vloc.send_frame(s, queries[0].jpeg, seq=0, wait=True)
            assert isinstance(pose, Pose) and pose.seq == 0
            assert (await vloc.send_frame(s, queries[1].jpeg, seq=1)).seq == 1
            await vloc.reset_session(s)
            await vloc.set_initial_pose(s, x=0.0, y=0.0, sigma=10.0)
            assert [p.seq for p in await vloc.list_poses(s, limit=1)] == [0]
            assert (await vloc.get_session(s)).mode == "hybrid"
            with pytest.raises(Conflict):
                await vloc.send_frame(s, queries[1].jpeg, seq=1)
            with pytest.raises(Conflict):
                await vloc.delete_map(m.id)
            await vloc.delete_session(s)
            await vloc.delete_map(m.id)
            with pytest.raises(NotFound):
                await vloc.get_map(m.id)
            with pytest.raises(BadRequest):
                await vloc.request("POST", "/v1/maps", content=b"{}",
                                   headers={"content-length": "-1"})
            assert (await vloc.ready())["status"] == "ready"


# -- error mapping and retries (scripted answers) --------------------------------------------


@pytest.mark.parametrize(("status", "cls"), [
    (400, BadRequest), (401, Unauthorized), (403, Forbidden), (404, NotFound), (409, Conflict),
    (413, PayloadTooLarge), (415, UnsupportedMediaType), (422, UnprocessableEntity),
    (429, TooManyRequests), (500, ServerError), (502, ServerError), (503, ServerError),
    (504, ServerError), (418, APIError)])
def test_status_to_class(status, cls):
    problem = {"type": "urn:vloc:problem:x", "title": "T", "status": status, "detail": "d",
               "instance": "/p", "extra": 1}
    err = error_for_response(httpx.Response(status, json=problem,
                                            headers={"content-type": "application/problem+json"}))
    assert type(err) is cls and isinstance(err, APIError) and isinstance(err, VlocError)
    assert (err.status, err.type, err.title, err.detail, err.instance, err.kind) == \
        (status, "urn:vloc:problem:x", "T", "d", "/p", "x")
    assert err.body["extra"] == 1


def test_non_json_error_body():
    err = error_for_response(httpx.Response(502, text="<html>Bad gateway</html>"))
    assert type(err) is ServerError and err.detail == "<html>Bad gateway</html>"
    assert err.type == "about:blank" and err.kind is None and err.title == "Bad Gateway"


class Script:
    """A MockTransport handler that answers from a list and records the requests."""

    def __init__(self, *answers) -> None:
        self.answers = list(answers)
        self.requests: list[httpx.Request] = []

    def __call__(self, request: httpx.Request) -> httpx.Response:
        self.requests.append(request)
        answer = self.answers.pop(0)
        if isinstance(answer, Exception):
            raise answer
        return answer


def problem(status: int, kind: str = "x", headers=None, **extra) -> httpx.Response:
    return httpx.Response(status, json={"type": f"urn:vloc:problem:{kind}", "title": "t",
                                        "status": status, "detail": "d", **extra},
                          headers=headers)


def scripted(*answers, retries: int = 3) -> tuple[Client, Script, list[float]]:
    script, sleeps = Script(*answers), []
    vloc = Client("http://vloc.test", admin_key="k", transport=httpx.MockTransport(script),
                  retry=RetryPolicy(retries=retries, backoff=0.1, max_delay=2.0),
                  sleep=sleeps.append)
    return vloc, script, sleeps


def test_get_is_retried_on_503_with_backoff():
    ok = httpx.Response(200, json=[])
    vloc, script, sleeps = scripted(problem(503), problem(502), ok)
    assert vloc.list_maps() == []
    assert len(script.requests) == 3 and len(sleeps) == 2
    # Full jitter within [cap/2, cap], the cap doubling per attempt.
    assert 0.05 <= sleeps[0] <= 0.1 and 0.1 <= sleeps[1] <= 0.2
    assert script.requests[0].headers["authorization"] == "Bearer k"


def test_retries_give_up_after_the_budget():
    vloc, script, sleeps = scripted(*[problem(504)] * 3, retries=2)
    with pytest.raises(ServerError) as info:
        vloc.get_map("m")
    assert info.value.status == 504 and len(script.requests) == 3 and len(sleeps) == 2


def test_retry_after_is_honoured():
    vloc, _, sleeps = scripted(problem(429, headers={"Retry-After": "1.5"}),
                               httpx.Response(202, json={"seq": 7}))
    assert vloc.send_frame("s", b"\xff\xd8\xff...", seq=7, token="t").seq == 7
    assert sleeps == [1.5]


def test_post_without_seq_is_not_retried():
    vloc, script, _ = scripted(problem(503), httpx.Response(201, json={}))
    with pytest.raises(ServerError):
        vloc.create_map("x")
    with pytest.raises(ServerError):
        scripted(problem(503))[0].send_frame("s", b"\x89PNG\r\n\x1a\n", token="t")
    assert len(script.requests) == 1


def test_connect_errors_retried_only_when_safe():
    vloc, script, _ = scripted(httpx.ConnectError("refused"),
                               httpx.Response(202, json={"seq": 3}))
    assert vloc.send_frame("s", b"\xff\xd8\xff", seq=3, token="t") == FrameAccepted(seq=3)
    assert script.requests[1].url.params["seq"] == "3"
    assert script.requests[1].headers["authorization"] == "Bearer t"
    assert script.requests[1].headers["content-type"] == "image/jpeg"
    vloc, script, _ = scripted(httpx.ConnectError("refused"))
    with pytest.raises(TransportError) as info:
        vloc.send_frame("s", b"\xff\xd8\xff", token="t")
    assert isinstance(info.value.__cause__, httpx.ConnectError) and len(script.requests) == 1
    # A read timeout may mean the server got the request: only connect failures retry.
    vloc, script, _ = scripted(httpx.ReadTimeout("slow"))
    with pytest.raises(TransportError):
        vloc.get_map("m")
    assert len(script.requests) == 1


def test_retried_frame_answered_duplicate_counts_as_accepted():
    vloc, _, _ = scripted(problem(503), problem(409, "duplicate-seq", last_seq=9))
    assert vloc.send_frame("s", b"\xff\xd8\xff", seq=9, token="t") == FrameAccepted(seq=9)
    # On a first attempt the same answer is a real conflict.
    vloc, _, _ = scripted(problem(409, "duplicate-seq", last_seq=9))
    with pytest.raises(Conflict):
        vloc.send_frame("s", b"\xff\xd8\xff", seq=9, token="t")


def test_nothing_listening_is_a_transport_error():
    port = free_port()  # nothing listens there
    with Client(f"http://127.0.0.1:{port}", retry=0) as vloc, pytest.raises(TransportError):
        vloc.health()
    with pytest.raises(WaitTimeout):
        Client(f"http://127.0.0.1:{port}").wait_ready(timeout=0)


def test_environment_configures_the_client(monkeypatch):
    monkeypatch.setenv("VLOC_URL", "http://example.test:9000/")
    monkeypatch.setenv("VLOC_ADMIN_KEY", "from-env")
    vloc = Client()
    assert (vloc.base_url, vloc.admin_key) == ("http://example.test:9000", "from-env")
    assert Client("http://other", admin_key="given").admin_key == "given"


def test_public_surface():
    assert clients.Client is Client and clients.NotFound is NotFound
    assert set(clients.__all__) == set(__import__("vloc.clients.sdk").clients.sdk.__all__)
    for name in clients.__all__:
        assert getattr(clients, name) is getattr(clients.sdk, name)
    with pytest.raises(AttributeError):
        clients.NoSuchThing  # noqa: B018


def test_the_sdk_knows_every_problem_kind_of_the_server():
    from vloc.app.problems import ProblemKind as ServerKind

    assert {k.name: k.value for k in clients.ProblemKind} == \
        {k.name: k.value for k in ServerKind}


def test_images_are_typed_by_their_bytes():
    from vloc.clients.sdk._requests import image_content_type

    assert image_content_type(b"\xff\xd8\xff\xe0") == "image/jpeg"
    assert image_content_type(b"\x89PNG\r\n\x1a\n....") == "image/png"
    assert image_content_type(b"????", "x.png") == "image/png"
    assert image_content_type(b"????", "x") == "application/octet-stream"
    assert np.isfinite(RetryPolicy().delay(10))


def test_the_422_class_no_longer_shadows_pydantic():
    import vloc.clients.sdk as sdk

    assert not hasattr(sdk, "__all__") or "ValidationError" not in sdk.__all__
    with pytest.warns(DeprecationWarning, match="UnprocessableEntity"):
        old = sdk.ValidationError
    assert old is UnprocessableEntity
    assert error_class(410) is sdk.Gone and error_class(422) is UnprocessableEntity


def test_listings_are_read_page_by_page(vloc, shots, monkeypatch):
    from vloc.clients.sdk import _requests

    m = vloc.create_map("paged")
    vloc.upload_images(m.id, [s.jpeg for s in shots[0][:5]])
    monkeypatch.setattr(_requests, "PAGE", 2)
    pages = []
    call = _requests.list_images
    monkeypatch.setattr(_requests, "list_images",
                        lambda *a, **k: pages.append(k) or call(*a, **k))
    monkeypatch.setattr(_requests, "next_offset", lambda c, items, offset: items[-1].id
                        if c is _requests.list_images else offset + len(items))
    images = vloc.list_images(m.id)
    assert len(images) == 5 and len({i.id for i in images}) == 5 and len(pages) == 3
    assert m.id in {x.id for x in vloc.list_maps()}
    vloc.delete_map(m.id)


def test_localize_coverage_and_keep_alive(vloc, session, shots):
    from vloc.clients.sdk import Localization

    maps, queries = shots
    where = vloc.localize(session.map_id, queries[3].jpeg, prior=(queries[3].lat,
                                                                   queries[3].lon),
                          prior_sigma_m=30, seed=1, captured_at="2013-06-04T13:45:09Z")
    assert isinstance(where, Localization) and where.map_id == session.map_id
    assert where.horizontal_accuracy_m > 0 and where.image_filename is not None
    with pytest.raises(UnprocessableEntity):
        vloc.localize(session.map_id, queries[3].jpeg, prior_sigma_m=5)
    covered = vloc.coverage(maps[0].lat, maps[0].lon)
    assert session.map_id in [c.map_id for c in covered]
    assert vloc.coverage(maps[0].lat + 1.0, maps[0].lon) == []
    alive = vloc.keep_alive(session)
    assert alive.state == "active" and alive.expires_at > alive.last_active_at
