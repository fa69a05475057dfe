"""Text from clients is free of NUL characters before anything stores it: JSON bodies,
query strings, uploaded file names and form fields are refused with 422 ``bad-text`` (on
PostgreSQL a NUL reaching a text column was a 500) and nothing changes."""

from __future__ import annotations

import pytest

from tests.app.conftest import ADMIN, PROBLEM, snapshot


def _refused(r) -> None:
    assert r.status_code == 422, r.text
    assert r.headers["content-type"] == PROBLEM
    assert r.json()["type"] == "urn:vloc:problem:bad-text"


def _multipart(filename: bytes, data: bytes) -> tuple[bytes, str]:
    """A one-file body written out by hand (clients percent-encode a NUL)."""
    boundary = "vloc-boundary"
    body = (f"--{boundary}\r\n".encode()
            + b'Content-Disposition: form-data; name="files"; filename="' + filename
            + b'"\r\nContent-Type: image/jpeg\r\n\r\n' + data
            + f"\r\n--{boundary}--\r\n".encode())
    return body, f"multipart/form-data; boundary={boundary}"


def test_a_nul_in_an_uploaded_file_name_is_refused(service, shots):
    c = service.client
    before = snapshot(c)
    body, content_type = _multipart(b"frame\x00.jpg", shots[1][0].jpeg)
    r = c.post(f"/v1/maps/{service.map_id}/images", content=body,
               headers=ADMIN | {"Content-Type": content_type})
    _refused(r)
    assert r.json()["field"] == "filename"
    assert snapshot(c) == before


def test_a_nul_in_a_route_name_or_its_odometry_is_refused(service):
    c = service.client
    before = snapshot(c)
    csv = b"filename,x,y,theta\nmap_000.jpg,0,0,0\nmap_001.jpg,1,0,0\nmap_002.jpg,2,0,0\n"
    r = c.post(f"/v1/maps/{service.map_id}/routes", headers=ADMIN,
               data={"name": "taught\x00"}, files={"odometry": ("o.csv", csv, "text/csv")})
    _refused(r)
    r = c.post(f"/v1/maps/{service.map_id}/routes", headers=ADMIN, data={"name": "taught"},
               files={"odometry": ("o.csv", csv.replace(b"map_001", b"map\x00001"),
                                   "text/csv")})
    assert r.status_code == 422 and "NUL" in r.json()["detail"]
    assert snapshot(c) == before


@pytest.mark.parametrize("body", [
    '{"name": "a\\u0000b"}',
    '{"name": "ok", "description": "\\\\\\u0000"}',
])
def test_a_nul_escape_in_a_json_body_is_refused(service, body):
    c = service.client
    before = snapshot(c)
    r = c.post("/v1/maps", headers=ADMIN | {"Content-Type": "application/json"},
               content=body.encode())
    _refused(r)
    assert snapshot(c) == before


def test_an_escaped_backslash_before_u0000_is_text(service):
    r = service.client.post("/v1/maps", headers=ADMIN, json={"name": "back\\u0000slash"})
    assert r.status_code == 201, r.text
    assert r.json()["name"] == "back\\u0000slash"
    service.client.delete(f"/v1/maps/{r.json()['id']}", headers=ADMIN)


def test_a_nul_in_the_query_string_is_refused(service):
    c = service.client
    _refused(c.get("/v1/maps?limit=1%00", headers=ADMIN))
    _refused(c.get("/v1/maps", params={"x": "\x00"}, headers=ADMIN))
