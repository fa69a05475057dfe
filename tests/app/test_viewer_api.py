"""What the web viewer reads: the particle sample on the stream only, image files, the last
frame, and the static pages."""

from __future__ import annotations

import hashlib

import pydantic
import pytest

from tests.app.conftest import ADMIN
from tests.app.test_frames import settled
from vloc.app.config import Settings


def test_streamed_pose_carries_a_cloud_sample_that_is_not_stored(service, shots):
    sid, auth = service.new_session()
    frame = shots[1][0].jpeg
    with service.client.websocket_connect(f"/v1/sessions/{sid}/stream", headers=auth) as ws:
        assert ws.receive_json()["type"] == "hello"
        ws.send_bytes(frame)
        pose = ws.receive_json()
    assert pose["type"] == "pose"
    cloud = pose["cloud"]
    assert 1 <= len(cloud) <= 64 and all(len(p) == 2 for p in cloud)
    assert pose["measurement"]
    r = service.client.get(f"/v1/maps/{service.map_id}", headers=ADMIN).json()
    ext = r["local_extent"]
    # the filter's particles live over the map's extent plus a margin
    span = max(ext["max_east"] - ext["min_east"], ext["max_north"] - ext["min_north"])
    for x, y in cloud:
        assert ext["min_east"] - span <= x <= ext["max_east"] + span
        assert ext["min_north"] - span <= y <= ext["max_north"] + span
    settled(service.client, sid, auth)  # the stream runs ahead of the database
    stored = service.client.get(f"/v1/sessions/{sid}/poses", headers=auth).json()
    assert [p["seq"] for p in stored] == [pose["seq"]]
    assert stored[0]["cloud"] == []  # the sample is not kept
    assert stored[0]["x"] == pose["x"]


def test_last_frame_is_served_to_its_session_only(service, shots):
    sid, auth = service.new_session()
    other, other_auth = service.new_session()
    r = service.client.get(f"/v1/sessions/{sid}/frames/last", headers=auth)
    assert r.status_code == 204 and r.content == b""
    frames = [shots[1][0].jpeg, shots[1][1].jpeg]
    for data in frames:
        r = service.client.post(f"/v1/sessions/{sid}/frames?wait=true", content=data,
                                headers=auth | {"Content-Type": "image/jpeg"})
        assert r.status_code == 200, r.text
    r = service.client.get(f"/v1/sessions/{sid}/frames/last", headers=auth)
    assert r.status_code == 200
    assert r.headers["content-type"] == "image/jpeg"
    assert r.headers["x-frame-seq"] == "1"
    assert r.content == frames[1]
    assert service.client.get(f"/v1/sessions/{sid}/frames/last",
                              headers=other_auth).status_code == 403
    assert service.client.get(f"/v1/sessions/{sid}/frames/last").status_code == 401


def test_map_image_file_is_the_upload_for_the_admin_only(service, shots):
    images = service.client.get(f"/v1/maps/{service.map_id}/images", headers=ADMIN).json()
    first = images[0]
    r = service.client.get(f"/v1/maps/{service.map_id}/images/{first['id']}/file",
                           headers=ADMIN)
    assert r.status_code == 200
    assert r.headers["content-type"] == first["content_type"]
    assert len(r.content) == first["byte_size"]
    assert hashlib.sha256(r.content).hexdigest() == first["file_hash"]
    _, token = service.new_session()
    assert service.client.get(f"/v1/maps/{service.map_id}/images/{first['id']}/file",
                              headers=token).status_code == 403
    missing = max(i["id"] for i in images) + 1000
    r = service.client.get(f"/v1/maps/{service.map_id}/images/{missing}/file", headers=ADMIN)
    assert r.status_code == 404
    assert r.headers["content-type"] == "application/problem+json"


def test_the_viewer_pages_are_served_without_credentials(service):
    r = service.client.get("/ui/")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    page = r.text
    assert "vendor/leaflet/leaflet.js" in page and "main.js" in page
    # no resource from elsewhere: the page works offline
    assert "http://" not in page and "https://" not in page
    for path in ("/ui/main.js", "/ui/common.js", "/ui/maps.js", "/ui/live.js",
                 "/ui/replays.js", "/ui/viewer.css", "/ui/vendor/leaflet/leaflet.js",
                 "/ui/vendor/leaflet/leaflet.css"):
        r = service.client.get(path)
        assert r.status_code == 200, path
    # module scripts load only with a JavaScript type
    assert service.client.get("/ui/main.js").headers["content-type"].split(";")[0] in (
        "text/javascript", "application/javascript")
    assert service.client.get("/ui/missing.js").status_code == 404


def test_ui_without_a_slash_redirects(service):
    r = service.client.get("/ui", follow_redirects=False)
    assert r.status_code == 308 and r.headers["location"] == "/ui/"


def test_viewer_config_has_no_tiles_unless_configured(service):
    assert service.client.get("/ui/config.json").json() == {"tile_url": None,
                                                            "tile_attribution": ""}


def test_tile_url_must_be_a_z_x_y_template(tmp_path):
    good = "https://tile.example.org/{z}/{x}/{y}.png"
    assert Settings(data_dir=tmp_path, viewer_tile_url=good).viewer_tile_url == good
    for bad in ("https://tile.example.org/tiles.png", "ftp://t/{z}/{x}/{y}",
                "https://t/{z}/{x}/{y} .png"):
        with pytest.raises(pydantic.ValidationError, match="viewer_tile_url"):
            Settings(data_dir=tmp_path, viewer_tile_url=bad)


def test_stream_sends_geojson_features_when_asked(service, shots):
    sid, auth = service.new_session()
    token = auth["Authorization"].split()[1]
    with service.client.websocket_connect(
            f"/v1/sessions/{sid}/stream",
            subprotocols=["vloc.geojson", f"vloc.token.{token}"]) as ws:
        assert ws.accepted_subprotocol == "vloc.geojson"
        assert ws.receive_json()["type"] == "hello"  # not a pose: as it is
        ws.send_bytes(shots[1][0].jpeg)
        feature = ws.receive_json()
    settled(service.client, sid, auth)
    (pose,) = service.client.get(f"/v1/sessions/{sid}/poses", headers=auth).json()
    assert feature["type"] == "Feature" and feature["id"] == pose["seq"] == 0
    assert feature["geometry"] == {"type": "Point", "coordinates": [pose["lon"], pose["lat"]]}
    props = feature["properties"]
    assert props["message"] == "pose"
    for key in ("x", "y", "cov", "sigma_x", "sigma_y", "status", "feature", "latency_ms"):
        assert props[key] == pose[key], key
    assert 0 < len(props["cloud"]) <= 64 and props["measurement"]
