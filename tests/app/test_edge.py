"""The edge gate: credentials before bodies, a body limit per kind of route.

Requests go through the whole application (middlewares, routes, database). Where a test
must see how much of a body was read, it calls the ASGI application directly with a body
that arrives in chunks and counts the chunks taken.
"""

from __future__ import annotations

import json
from collections.abc import Iterator

import pytest
from fastapi.testclient import TestClient

from tests.app.conftest import ADMIN, PROBLEM, backend_client, snapshot

JSON_LIMIT = 4096
FRAME_LIMIT = 400_000


@pytest.fixture(scope="module",
                params=["sqlite", pytest.param("postgres", marks=pytest.mark.postgres)])
def edge_client(request, tmp_path_factory) -> Iterator[TestClient]:
    yield from backend_client(request.param, tmp_path_factory, max_json_bytes=JSON_LIMIT,
                              max_frame_bytes=FRAME_LIMIT,
                              metrics_token="metrics-token-0123456789")


def asgi_post(client: TestClient, path: str, headers: dict[str, str], chunks: int,
              chunk: bytes = b"x" * 65536) -> tuple[int, dict[str, str], dict, int]:
    """POST a body of ``chunks`` chunks straight to the ASGI app.

    Returns the status, the response headers, the JSON body and how many chunks the
    application took.
    """
    taken = 0
    sent: list[dict] = []

    async def receive() -> dict:
        nonlocal taken
        if taken < chunks:
            taken += 1
            return {"type": "http.request", "body": chunk, "more_body": taken < chunks}
        return {"type": "http.disconnect"}

    async def send(message: dict) -> None:
        sent.append(message)

    raw = [(k.lower().encode(), v.encode()) for k, v in headers.items()]
    scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1",
             "method": "POST", "scheme": "http", "path": path, "raw_path": path.encode(),
             "query_string": b"", "root_path": "", "headers": raw,
             "client": ("127.0.0.1", 5000), "server": ("testserver", 80), "state": {}}
    client.portal.call(client.app, scope, receive, send)
    start = next(m for m in sent if m["type"] == "http.response.start")
    body = b"".join(m.get("body", b"") for m in sent if m["type"] == "http.response.body")
    out_headers = {k.decode().lower(): v.decode() for k, v in start["headers"]}
    return start["status"], out_headers, json.loads(body), taken


def new_map(client: TestClient) -> str:
    r = client.post("/v1/maps", json={"name": "edge"}, headers=ADMIN)
    assert r.status_code == 201, r.text
    return r.json()["id"]


# -- credentials before the body -------------------------------------------------------------

@pytest.mark.parametrize(("headers", "status"), [
    ({}, 401), ({"Authorization": "Bearer not-the-admin-key"}, 403),
    ({"X-API-Key": "not-the-admin-key"}, 403)])
def test_malformed_json_is_refused_for_credentials_first(edge_client, headers, status):
    before = snapshot(edge_client)
    r = edge_client.post("/v1/maps", content=b'{"name": ',
                         headers={**headers, "Content-Type": "application/json"})
    assert r.status_code == status and r.headers["content-type"] == PROBLEM
    assert r.json()["type"] == ("urn:vloc:problem:unauthenticated" if status == 401
                                else "urn:vloc:problem:forbidden")
    if status == 401:
        assert r.headers["www-authenticate"].startswith("Bearer")
    assert snapshot(edge_client) == before


def test_malformed_json_with_the_admin_key_is_a_validation_problem(edge_client):
    r = edge_client.post("/v1/maps", content=b'{"name": ',
                         headers={**ADMIN, "Content-Type": "application/json"})
    assert r.status_code == 422 and r.json()["type"] == "urn:vloc:problem:validation"


@pytest.mark.parametrize("path", ["/v1/maps", "/v1/maps/{map}/images"])
def test_an_unauthenticated_body_is_never_read(edge_client, path):
    before = snapshot(edge_client)
    path = path.format(map=new_map(edge_client))
    before = snapshot(edge_client)
    # 200 chunks of 64 KiB declared (13 MB): none of it is read.
    status, headers, body, taken = asgi_post(
        edge_client, path, {"Content-Type": "application/json",
                            "Content-Length": str(200 * 65536)}, chunks=200)
    assert (status, taken) == (401, 0)
    assert headers["connection"] == "close" and body["status"] == 401
    # The same body streamed without a length.
    status, _, _, taken = asgi_post(
        edge_client, path, {"Content-Type": "multipart/form-data; boundary=x",
                            "Transfer-Encoding": "chunked", "Authorization": "Bearer wrong"},
        chunks=200)
    assert (status, taken) == (403, 0)
    assert snapshot(edge_client) == before


def test_a_session_route_checks_the_token_before_the_body(edge_client):
    from vloc.app.security import hash_secret

    ctx = edge_client.app.state.ctx
    sid = _session_row(ctx, token_hash=hash_secret("the-right-session-token"))
    before = snapshot(edge_client)
    frames = f"/v1/sessions/{sid}/frames"
    for headers, status in (({}, 401), ({"Authorization": "Bearer wrong-token"}, 403)):
        got, _, body, taken = asgi_post(edge_client, frames, {
            **headers, "Content-Type": "image/jpeg", "Transfer-Encoding": "chunked"},
            chunks=200)
        assert (got, taken) == (status, 0), body
    got, _, body, taken = asgi_post(
        edge_client, "/v1/sessions/00000000-0000-0000-0000-000000000000/frames",
        {"Authorization": "Bearer wrong-token", "Content-Type": "image/jpeg"}, chunks=200)
    assert (got, taken, body["type"]) == (404, 0, "urn:vloc:problem:not-found")
    r = edge_client.post(f"/v1/sessions/{sid}/initial-pose", content=b"{oops",
                         headers={"Content-Type": "application/json"})
    assert r.status_code == 401
    assert snapshot(edge_client) == before


def _session_row(ctx, *, token_hash: str) -> str:
    """A session row of a map that was never built (enough for the gate)."""
    from vloc.app.maps.models import Map
    from vloc.app.sessions.models import LocalisationSession

    with ctx.db_sessions() as db:
        m = Map(name="gate", status="empty", revision=0)
        db.add(m)
        db.flush()
        row = LocalisationSession(map_id=m.id, map_revision=1, mode="hybrid", params={},
                                  seed=1, token_hash=token_hash, frames_processed=0,
                                  frames_failed=0)
        db.add(row)
        db.commit()
        return str(row.id)


# -- one body limit per kind of route --------------------------------------------------------

def test_json_bodies_have_their_own_small_limit(edge_client):
    before = snapshot(edge_client)
    big = json.dumps({"name": "x" * 100, "pad": "y" * JSON_LIMIT}).encode()
    r = edge_client.post("/v1/maps", content=big,
                         headers={**ADMIN, "Content-Type": "application/json"})
    assert r.status_code == 413 and r.headers["content-type"] == PROBLEM
    assert r.json()["limit"] == JSON_LIMIT
    # Streamed without a Content-Length: refused once the limit is passed, not at the end.
    status, headers, body, taken = asgi_post(
        edge_client, "/v1/maps", {**ADMIN, "Content-Type": "application/json",
                                  "Transfer-Encoding": "chunked"}, chunks=50, chunk=b" " * 1024)
    assert (status, body["type"]) == (413, "urn:vloc:problem:too-large")
    assert taken == JSON_LIMIT // 1024 + 1 and headers["connection"] == "close"
    assert snapshot(edge_client) == before


def test_uploads_and_frames_take_more_than_a_json_body(edge_client, shots):
    map_id = new_map(edge_client)
    files = [("files", (s.name, s.jpeg, "image/jpeg")) for s in shots[0][:3]]
    r = edge_client.post(f"/v1/maps/{map_id}/images", files=files, headers=ADMIN)
    assert r.status_code == 201 and len(r.json()["accepted"]) == 3
    assert int(r.request.headers["content-length"]) > JSON_LIMIT
    # A frame body goes up to the frame limit and no further.
    sid = _session_row(edge_client.app.state.ctx, token_hash="0" * 64)
    status, _, body, taken = asgi_post(
        edge_client, f"/v1/sessions/{sid}/frames",
        {**ADMIN, "Content-Type": "image/jpeg", "Content-Length": str(FRAME_LIMIT + 1)},
        chunks=10)
    assert (status, body["limit"], taken) == (413, FRAME_LIMIT, 0)


def test_an_invalid_content_length_is_a_bad_request(edge_client):
    status, _, body, taken = asgi_post(
        edge_client, "/v1/maps", {**ADMIN, "Content-Length": "-5"}, chunks=1)
    assert (status, body["type"], taken) == (400, "urn:vloc:problem:bad-request", 0)


# -- metrics, 405, files ---------------------------------------------------------------------

@pytest.mark.parametrize(("headers", "status"), [
    ({}, 401), ({"Authorization": "Bearer wrong-token-000000"}, 403),
    ({"Authorization": "Bearer metrics-token-0123456789"}, 200), (ADMIN, 200)])
def test_metrics_need_the_metrics_token_or_the_admin_key(edge_client, headers, status):
    r = edge_client.get("/metrics", headers=headers)
    assert r.status_code == status
    if status == 200:
        assert "vloc_http_requests_total" in r.text
    else:
        assert r.headers["content-type"] == PROBLEM and "vloc_" not in r.text


@pytest.mark.parametrize(("method", "path", "allow"), [
    ("PUT", "/v1/maps", {"GET", "POST"}),
    ("PATCH", "/v1/maps/{map}", {"GET", "DELETE"}),
    ("PUT", "/v1/sessions/{sid}", {"GET", "DELETE"}),
    ("GET", "/v1/maps/{map}/build", {"POST"}),
])
def test_405_lists_every_allowed_method(edge_client, method, path, allow):
    map_id = new_map(edge_client)
    sid = _session_row(edge_client.app.state.ctx, token_hash="0" * 64)
    before = snapshot(edge_client)
    url = path.format(map=map_id, sid=sid)
    r = edge_client.request(method, url, headers=ADMIN)
    assert r.status_code == 405 and r.headers["content-type"] == PROBLEM
    assert set(r.headers["allow"].replace(" ", "").split(",")) >= allow
    assert snapshot(edge_client) == before


def test_data_dir_and_sqlite_file_are_private(tmp_path):
    import stat

    from tests.app.conftest import service_settings
    from vloc.app.main import create_app

    data = tmp_path / "data"
    data.mkdir(mode=0o755)
    data.chmod(0o755)
    settings = service_settings(data, None)
    settings.database_url = None
    with TestClient(create_app(settings)) as c:
        assert c.get("/healthz").status_code == 200
    assert stat.S_IMODE(data.stat().st_mode) == 0o700
    db = data / "vloc.sqlite3"
    assert stat.S_IMODE(db.stat().st_mode) == 0o600
    for extra in data.glob("vloc.sqlite3-*"):
        assert stat.S_IMODE(extra.stat().st_mode) & 0o077 == 0


def test_the_gate_policies_match_the_documented_security(edge_client):
    """The gate's path table and the routes' own security dependencies (as the OpenAPI
    description states them) agree on every operation."""
    import re

    from vloc.app.edge import Access, policy_for

    expected = {frozenset(): Access.PUBLIC,
                frozenset({"adminKey", "adminApiKey"}): Access.ADMIN,
                frozenset({"sessionToken", "adminKey", "adminApiKey"}): Access.SESSION}
    spec = edge_client.get("/openapi.json").json()
    checked = 0
    for path, operations in spec["paths"].items():
        concrete = re.sub(r"\{[^}]+\}", "00000000-0000-0000-0000-000000000001", path)
        for method, operation in operations.items():
            schemes = frozenset(name for req in operation.get("security", []) for name in req)
            policy, _ = policy_for(method.upper(), concrete)
            assert policy.access is expected[schemes], (method, path)
            checked += 1
    assert checked >= 19
