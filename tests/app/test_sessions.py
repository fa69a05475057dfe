"""Session routes against the real app and core: create, auth, frames, stream, controls."""

from __future__ import annotations

import uuid

import pytest
from starlette.websockets import WebSocketDisconnect

from tests.app.conftest import ADMIN, FAST, PROBLEM, UNKNOWN_ID, jpeg_files, snapshot
from tests.app.imagery import plain_jpeg, png, png_bomb
from tests.app.test_maps import corrupt_png, new_map

JPEG = {"Content-Type": "image/jpeg"}


def post_frame(client, sid, data, auth, ctype="image/jpeg", **params):
    headers = {**auth, "Content-Type": ctype} if ctype else dict(auth)
    return client.post(f"/v1/sessions/{sid}/frames", content=data, headers=headers,
                       params={k: v for k, v in params.items() if v is not None})


def open_stream(client, sid, token_or_auth):
    token = token_or_auth["Authorization"].split()[1] \
        if isinstance(token_or_auth, dict) else token_or_auth
    ws = client.websocket_connect(f"/v1/sessions/{sid}/stream?token={token}")
    return ws


def test_create_read_list_delete(service):
    c = service.client
    r = c.post("/v1/sessions", headers=ADMIN, json={
        "map_id": service.map_id, "mode": "hybrid", "params": {"n_particles": 60}, "seed": 5})
    assert r.status_code == 201, r.text
    body = r.json()
    assert r.headers["location"] == f"/v1/sessions/{body['id']}"
    assert (body["mode"], body["seed"], body["map_revision"], body["last_seq"]) == \
        ("hybrid", 5, 1, None)
    assert body["params"]["n_particles"] == 60 and "motion_sigma" in body["params"]
    assert len(body["token"]) >= 40
    auth = {"Authorization": f"Bearer {body['token']}"}
    got = c.get(f"/v1/sessions/{body['id']}", headers=auth).json()
    assert "token" not in got and got["id"] == body["id"]
    assert got == c.get(f"/v1/sessions/{body['id']}", headers=ADMIN).json()
    assert body["id"] in {s["id"] for s in c.get("/v1/sessions", headers=ADMIN).json()}
    # The token is stored as a hash only.
    with c.app.state.ctx.db_sessions() as db:
        from vloc.app.sessions.models import LocalisationSession

        row = db.get(LocalisationSession, uuid.UUID(body["id"]))
        assert body["token"] not in row.token_hash and len(row.token_hash) == 64
    assert c.delete(f"/v1/sessions/{body['id']}", headers=auth).status_code == 204
    assert c.get(f"/v1/sessions/{body['id']}", headers=ADMIN).status_code == 404
    assert c.get(f"/v1/sessions/{body['id']}", headers=auth).status_code == 404


def test_seed_from_params_and_random_seed(service):
    c = service.client
    sid, auth = service.new_session(params={**FAST, "seed": 11}, seed=None)
    assert c.get(f"/v1/sessions/{sid}", headers=auth).json()["seed"] == 11
    sid2, auth2 = service.new_session(seed=None)
    assert 0 <= c.get(f"/v1/sessions/{sid2}", headers=auth2).json()["seed"] < 2**63


BAD_CREATES = {
    "unknown-mode": ({"mode": "teleport"}, 422, "validation"),
    "bad-param": ({"params": {"n_particles": -3}}, 422, "validation"),
    "unknown-param": ({"mode": "retrieval", "params": {"bogus": 1}}, 422, "validation"),
    "seeds-disagree": ({"params": {"seed": 1}, "seed": 2}, 422, "bad-params"),
    "negative-seed": ({"seed": -1}, 422, "validation"),
    "unknown-map": ({"map_id": str(uuid.uuid4())}, 404, "not-found"),
    "malformed-map-id": ({"map_id": "nope"}, 422, "validation"),
}


@pytest.mark.parametrize("case", sorted(BAD_CREATES))
def test_bad_session_create_changes_nothing(service, case):
    change, status, kind = BAD_CREATES[case]
    c = service.client
    before = snapshot(c)
    body = {"map_id": service.map_id, "mode": "hybrid", "params": {}} | change
    r = c.post("/v1/sessions", json=body, headers=ADMIN)
    assert r.status_code == status, r.text
    assert r.headers["content-type"] == PROBLEM and r.json()["type"] == f"urn:vloc:problem:{kind}"
    assert snapshot(c) == before


def test_session_on_an_unbuilt_map_is_409(service, shots):
    c = service.client
    map_id = new_map(c)
    c.post(f"/v1/maps/{map_id}/images", files=jpeg_files(shots[0][:1]), headers=ADMIN)
    before = snapshot(c)
    r = c.post("/v1/sessions", json={"map_id": map_id}, headers=ADMIN)
    assert r.status_code == 409 and r.json()["type"] == "urn:vloc:problem:map-not-built"
    assert snapshot(c) == before


def test_session_auth_rules(service):
    c = service.client
    sid, auth = service.new_session()
    other, other_auth = service.new_session()
    before = snapshot(c)
    # Creating needs the admin key; a session token is not one.
    assert c.post("/v1/sessions", json={"map_id": service.map_id}).status_code == 401
    assert c.post("/v1/sessions", json={"map_id": service.map_id},
                  headers=auth).status_code == 403
    assert c.get("/v1/sessions", headers=auth).status_code == 403
    for method, path in (("get", ""), ("delete", ""), ("get", "/poses"),
                         ("post", "/reset")):
        url = f"/v1/sessions/{sid}{path}"
        assert getattr(c, method)(url).status_code == 401
        assert getattr(c, method)(url, headers=other_auth).status_code == 403
        assert getattr(c, method)(url, headers={"Authorization": "Bearer x"}).status_code == 403
    # A session's token opens only its own session.
    assert post_frame(c, sid, plain_jpeg(), other_auth).status_code == 403
    assert post_frame(c, sid, plain_jpeg(), {}).status_code == 401
    # The token is not the admin key.
    assert c.get(f"/v1/maps/{service.map_id}", headers=auth).status_code == 403
    assert snapshot(c) == before
    assert c.get(f"/v1/sessions/{other}", headers=ADMIN).status_code == 200


@pytest.mark.parametrize("ident", [UNKNOWN_ID, "not-a-uuid"])
def test_unknown_session_is_404(service, ident):
    c = service.client
    before = snapshot(c)
    for method, path in (("get", ""), ("delete", ""), ("post", "/reset"), ("get", "/poses")):
        r = getattr(c, method)(f"/v1/sessions/{ident}{path}", headers=ADMIN)
        assert r.status_code == 404 and r.json()["type"] == "urn:vloc:problem:not-found"
    assert post_frame(c, ident, plain_jpeg(), ADMIN).status_code == 404
    assert snapshot(c) == before


def test_frames_in_poses_out_in_order(service, shots):
    c = service.client
    sid, auth = service.new_session()
    queries = shots[1][:4]
    with open_stream(c, sid, auth) as ws:
        assert ws.receive_json() == {"type": "hello", "session_id": sid, "last_seq": None}
        seqs = []
        for i, q in enumerate(queries):
            r = post_frame(c, sid, q.jpeg, auth,
                           captured_at=q.captured_at.isoformat() if i % 2 else None)
            assert r.status_code == 202, r.text
            seqs.append(r.json()["seq"])
        assert seqs == [0, 1, 2, 3]
        poses = [ws.receive_json() for _ in queries]
    assert [p["type"] for p in poses] == ["pose"] * 4
    assert [p["seq"] for p in poses] == seqs
    assert poses[1]["captured_at"] == queries[1].captured_at.isoformat().replace("+00:00", "Z")
    assert poses[0]["captured_at"] is None
    for p in poses:
        assert p["session_id"] == sid and len(p["cov"]) == 4 and p["n_particles"] == 60
        assert p["feature"] in ("sift", "global") and p["status"] in (
            "initialising", "tracking", "lost")
        assert p["latency_ms"] >= p["processing_ms"] + p["decode_ms"]
        assert p["processing_ms"] > 0 and p["decode_ms"] > 0
    # wait=true answers with the estimate itself; the stored poses match the streamed ones.
    r = post_frame(c, sid, queries[0].jpeg, auth, wait="true")
    assert r.status_code == 200 and r.json()["type"] == "pose" and r.json()["seq"] == 4
    stored = c.get(f"/v1/sessions/{sid}/poses", headers=auth).json()
    assert [p["seq"] for p in stored] == [0, 1, 2, 3, 4]
    assert [(p["x"], p["y"], p["feature"]) for p in stored[:4]] == \
        [(p["x"], p["y"], p["feature"]) for p in poses]
    assert c.get(f"/v1/sessions/{sid}/poses", params={"after_seq": 2},
                 headers=auth).json()[0]["seq"] == 3
    s = c.get(f"/v1/sessions/{sid}", headers=auth).json()
    assert (s["last_seq"], s["frames_processed"], s["frames_failed"], s["frames_pending"]) == \
        (4, 5, 0, 0)
    assert s["last_pose"]["seq"] == 4 and s["stats"]["latency_ms_p50"] > 0
    assert s["stats"]["sift_share"] == sum(p["feature"] == "sift" for p in stored) / 5


def _bomb_png_declared(shots):
    return png_bomb(), "image/png"


BAD_FRAMES = {
    # name: (body builder, content type, query, status, problem kind)
    "text-content-type": (lambda s: s[1][0].jpeg, "text/plain", {}, 415,
                          "unsupported-media-type"),
    "octet-stream": (lambda s: s[1][0].jpeg, "application/octet-stream", {}, 415,
                     "unsupported-media-type"),
    "no-content-type": (lambda s: s[1][0].jpeg, None, {}, 415, "unsupported-media-type"),
    "png-declared-jpeg": (lambda s: png(), "image/jpeg", {}, 415, "content-type-mismatch"),
    "empty": (lambda s: b"", "image/jpeg", {}, 422, "empty-image"),
    "garbage": (lambda s: b"\x00\x01garbage" * 10, "image/jpeg", {}, 422, "bad-image"),
    "truncated": (lambda s: s[1][0].jpeg[:4000], "image/jpeg", {}, 422, "truncated-image"),
    "bomb": (lambda s: png_bomb(), "image/png", {}, 413, "too-many-pixels"),
    "too-large": (lambda s: s[1][0].jpeg + b"\x00" * 400_000, "image/jpeg", {}, 413,
                  "too-large"),
    "duplicate-seq": (lambda s: s[1][1].jpeg, "image/jpeg", {"seq": 5}, 409, "duplicate-seq"),
    "stale-seq": (lambda s: s[1][1].jpeg, "image/jpeg", {"seq": 2}, 409, "stale-seq"),
    "negative-seq": (lambda s: s[1][1].jpeg, "image/jpeg", {"seq": -1}, 422, "validation"),
    "bad-captured-at": (lambda s: s[1][1].jpeg, "image/jpeg", {"captured_at": "yesterday"},
                        422, "validation"),
}


@pytest.mark.parametrize("case", sorted(BAD_FRAMES))
def test_rejected_frame_changes_nothing(service, shots, case):
    build, ctype, query, status, kind = BAD_FRAMES[case]
    c = service.client
    sid, auth = service.new_session()
    assert post_frame(c, sid, shots[1][0].jpeg, auth, seq=5, wait="true").status_code == 200
    before = snapshot(c)
    r = post_frame(c, sid, build(shots), auth, ctype, **query)
    assert r.status_code == status, r.text
    assert r.headers["content-type"] == PROBLEM
    assert r.json()["type"] == f"urn:vloc:problem:{kind}" and r.json()["status"] == status
    assert snapshot(c) == before
    # The sequence goes on from where it was.
    r = post_frame(c, sid, shots[1][1].jpeg, auth, wait="true")
    assert r.status_code == 200 and r.json()["seq"] == 6


def test_frame_that_fails_in_the_worker_is_reported(service, shots):
    c = service.client
    sid, auth = service.new_session()
    with open_stream(c, sid, auth) as ws:
        ws.receive_json()
        assert post_frame(c, sid, corrupt_png(), auth, "image/png").json() == {"seq": 0}
        assert post_frame(c, sid, shots[1][0].jpeg, auth).json() == {"seq": 1}
        failed, pose = ws.receive_json(), ws.receive_json()
    assert (failed["type"], failed["seq"], failed["kind"]) == ("frame_error", 0, "bad_image")
    assert failed["reason"]
    assert (pose["type"], pose["seq"]) == ("pose", 1)
    r = post_frame(c, sid, corrupt_png(), auth, "image/png", wait="true")
    assert r.status_code == 422 and r.json()["type"] == "urn:vloc:problem:frame-bad-image"
    assert r.json()["seq"] == 2
    s = c.get(f"/v1/sessions/{sid}", headers=auth).json()
    assert (s["last_seq"], s["frames_processed"], s["frames_failed"]) == (2, 1, 2)


def test_frames_over_the_websocket(service, shots):
    c = service.client
    sid, auth = service.new_session()
    with open_stream(c, sid, auth) as ws:
        ws.receive_json()
        ws.send_bytes(shots[1][0].jpeg)
        ws.send_json({"type": "frame_meta", "seq": 10, "captured_at": "2024-06-04T13:40:00Z"})
        ws.send_bytes(shots[1][1].jpeg)
        ws.send_bytes(b"not an image")
        ws.send_json({"type": "ping"})
        ws.send_bytes(shots[1][2].jpeg)
        got = [ws.receive_json() for _ in range(5)]
    poses = [m for m in got if m["type"] == "pose"]
    assert [p["seq"] for p in poses] == [0, 10, 11]
    assert poses[1]["captured_at"] == "2024-06-04T13:40:00Z"
    (error,) = [m for m in got if m["type"] == "error"]
    assert error["problem"]["status"] == 422
    assert {"type": "pong"} in got


@pytest.mark.parametrize(("token", "code"), [(None, 4401), ("wrong", 4403)])
def test_stream_refuses_bad_tokens(service, token, code):
    c = service.client
    sid, _ = service.new_session()
    url = f"/v1/sessions/{sid}/stream" + (f"?token={token}" if token else "")
    with pytest.raises(WebSocketDisconnect) as info, c.websocket_connect(url) as ws:
        ws.receive_json()
    assert info.value.code == code


def test_stream_of_unknown_session_and_other_token(service):
    c = service.client
    _, auth = service.new_session()
    other, _ = service.new_session()
    for sid, code in ((str(uuid.uuid4()), 4404), ("nope", 4404), (other, 4403)):
        with pytest.raises(WebSocketDisconnect) as info, open_stream(c, sid, auth) as ws:
            ws.receive_json()
        assert info.value.code == code


def test_deleting_a_session_closes_its_stream(service):
    c = service.client
    sid, auth = service.new_session()
    with open_stream(c, sid, auth) as ws:
        ws.receive_json()
        assert c.delete(f"/v1/sessions/{sid}", headers=ADMIN).status_code == 204
        assert ws.receive_json()["type"] == "closed"
        with pytest.raises(WebSocketDisconnect):
            ws.receive_json()
    assert post_frame(c, sid, plain_jpeg(), auth).status_code == 404


def test_initial_pose_and_reset(service, shots):
    c = service.client
    sid, auth = service.new_session(params={**FAST, "replace_fraction": 0.0})
    target = shots[0][7]
    r = c.post(f"/v1/sessions/{sid}/initial-pose", headers=auth,
               json={"lat": target.lat, "lon": target.lon, "sigma": 1.0})
    assert r.status_code == 200 and r.json()["id"] == sid
    pose = post_frame(c, sid, target.jpeg, auth, wait="true").json()
    # The cloud starts within a metre or so of the map image; one step keeps it near.
    map_images = c.get(f"/v1/maps/{service.map_id}/images", headers=ADMIN).json()
    east, north = map_images[7]["east"], map_images[7]["north"]
    assert abs(pose["x"] - east) < 10 and abs(pose["y"] - north) < 10
    r = c.post(f"/v1/sessions/{sid}/initial-pose", headers=auth,
               json={"x": east, "y": north, "sigma": 2.0})
    assert r.status_code == 200
    assert c.post(f"/v1/sessions/{sid}/reset", headers=auth).status_code == 200
    assert post_frame(c, sid, target.jpeg, auth, wait="true").json()["seq"] == 1


@pytest.mark.parametrize("body", [
    {"lat": 95.0, "lon": 0.0}, {"lat": 41.0}, {"x": 1.0, "y": 2.0, "lat": 41.0, "lon": 1.0},
    {"x": 1.0, "y": 2.0, "sigma": 0}, {}])
def test_bad_initial_pose_is_422(service, body):
    c = service.client
    sid, auth = service.new_session()
    before = snapshot(c)
    r = c.post(f"/v1/sessions/{sid}/initial-pose", headers=auth, json=body)
    assert r.status_code == 422 and r.headers["content-type"] == PROBLEM
    assert snapshot(c) == before


def test_map_with_sessions_cannot_be_deleted(service):
    c = service.client
    service.new_session()
    before = snapshot(c)
    r = c.delete(f"/v1/maps/{service.map_id}", headers=ADMIN)
    assert r.status_code == 409 and r.json()["type"] == "urn:vloc:problem:map-in-use"
    assert snapshot(c) == before


def test_a_missing_map_revision_is_a_problem_without_the_data_path(service):
    """A session whose packed revision is gone from the data directory cannot be restored;
    the answer and the close reason name the map, never the files' path."""
    import shutil

    c = service.client
    ctx = c.app.state.ctx
    sid, auth = service.new_session()
    folder = ctx.settings.packed_map_dir(service.map_id, 1)
    hidden = folder.with_name(folder.name + ".away")
    ctx.sessions.forget(uuid.UUID(sid))  # as after a restart: restored on next use
    shutil.move(folder, hidden)
    try:
        before = snapshot(c)
        r = c.post(f"/v1/sessions/{sid}/reset", headers=auth)
        assert r.status_code == 503 and r.headers["content-type"] == PROBLEM
        assert r.json()["type"] == "urn:vloc:problem:map-revision-missing"
        data_dir = str(ctx.settings.data_dir.resolve())
        assert data_dir not in r.text and str(ctx.settings.data_dir) not in r.text
        with pytest.raises(WebSocketDisconnect) as info, open_stream(c, sid, auth) as ws:
            ws.receive_json()
        assert info.value.code == 1011 and data_dir not in (info.value.reason or "")
        assert "revision 1" in info.value.reason
        assert snapshot(c) == before
    finally:
        shutil.move(hidden, folder)
