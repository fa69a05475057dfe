"""A frame's sensor reports over HTTP and the WebSocket: validated at the edge (422 naming
the field, nothing recorded), forwarded to the localiser, reported back on the pose."""

from __future__ import annotations

import pytest

from tests.app.conftest import PROBLEM, snapshot
from tests.app.test_sessions import open_stream, post_frame
from vloc.workers.core.metadata import FrameMetadata

GOOD = {"heading_deg": 87.5, "heading_accuracy_deg": 4.0, "altitude_m": 212.5,
        "gps_lat": 41.0345, "gps_lon": -83.3057, "gps_accuracy_m": 8.0,
        "velocity_east": 1.5, "velocity_north": -0.5}


def test_metadata_reaches_the_localiser_and_comes_back_on_the_pose(service, shots,
                                                                  monkeypatch):
    c = service.client
    engine = c.app.state.ctx.engine
    sid, auth = service.new_session()
    sent = []
    submit = engine.submit_frame

    def spy(session_id, seq, data, **kwargs):
        sent.append(kwargs.get("metadata"))
        return submit(session_id, seq, data, **kwargs)

    monkeypatch.setattr(engine, "submit_frame", spy)
    r = post_frame(c, sid, shots[1][0].jpeg, auth, wait="true", **GOOD)
    assert r.status_code == 200, r.text
    p = r.json()
    assert p["altitude_m"] == 212.5 and p["geopose"]["position"]["h"] == 212.5
    # the heading is the geometry's where it solved one, else the device's own
    assert p["heading_source"] in ("geometry", "device")
    if p["heading_source"] == "device":
        assert (p["heading_deg"], p["heading_sigma_deg"]) == (87.5, 4.0)
    # the worker got every report, validated once here: the FrameMetadata itself
    assert isinstance(sent[0], FrameMetadata) and sent[0].to_dict() == GOOD
    assert set(filter(None, p["metadata_used"].split("+"))) <= {
        "heading", "gps", "altitude", "velocity"}
    plain = post_frame(c, sid, shots[1][1].jpeg, auth, wait="true").json()
    assert sent[1] is None
    assert (plain["altitude_m"], plain["gps_gate"]) == (None, "")


@pytest.mark.parametrize(("params", "field"), [
    ({"heading_deg": 360}, "heading_deg"),
    ({"heading_deg": -1}, "heading_deg"),
    ({"heading_deg": "nan"}, "heading_deg"),
    ({"altitude_m": "inf"}, "altitude_m"),
    ({"altitude_m": 20000}, "altitude_m"),
    ({"heading_deg": 10, "heading_accuracy_deg": -2}, "heading_accuracy_deg"),
    ({"heading_accuracy_deg": 5}, "heading_accuracy_deg"),
    ({"gps_lat": 41.0}, "gps_lat"),
    ({"gps_lon": -83.0}, "gps_lat"),
    ({"gps_lat": 91, "gps_lon": 0}, "gps_lat"),
    ({"gps_lat": 41, "gps_lon": -83, "gps_accuracy_m": 0}, "gps_accuracy_m"),
    ({"gps_accuracy_m": 5}, "gps_accuracy_m"),
    ({"gps_lat": 41, "gps_lon": -83, "gps_accuracy_m": 1e308}, "gps_accuracy_m"),
    ({"gps_lat": 41, "gps_lon": -83, "gps_accuracy_m": 1e-300}, "gps_accuracy_m"),
    ({"heading_deg": 10, "heading_accuracy_deg": 1e-300}, "heading_accuracy_deg"),
    ({"velocity_east": 1e308, "velocity_north": 1e308}, "velocity"),
    ({"velocity_east": 1.0}, "velocity_east"),
    ({"velocity_east": 200, "velocity_north": 0}, "velocity"),
])
def test_bad_metadata_is_422_naming_the_field_and_records_nothing(service, shots, params,
                                                                  field):
    c = service.client
    sid, auth = service.new_session()
    before = snapshot(c)
    r = post_frame(c, sid, shots[1][0].jpeg, auth, **params)
    assert r.status_code == 422 and r.headers["content-type"] == PROBLEM
    body = r.json()
    assert body["type"].endswith("bad-metadata") and field in body["detail"]
    if field != "velocity":
        assert body["field"] == field
    assert snapshot(c) == before
    assert c.get(f"/v1/sessions/{sid}", headers=auth).json()["last_seq"] is None


def test_not_a_number_is_422_from_the_query_parser(service, shots):
    c = service.client
    sid, auth = service.new_session()
    r = post_frame(c, sid, shots[1][0].jpeg, auth, heading_deg="east")
    assert r.status_code == 422 and "heading_deg" in r.text


def test_metadata_over_the_websocket(service, shots):
    c = service.client
    sid, auth = service.new_session()
    with open_stream(c, sid, auth) as ws:
        ws.receive_json()
        ws.send_json({"type": "frame_meta", "metadata": {"gps_lat": 41.0}})
        ws.send_bytes(shots[1][0].jpeg)
        refused = ws.receive_json()
        assert refused["type"] == "error"
        assert refused["problem"]["type"].endswith("bad-metadata")
        ws.send_json({"type": "frame_meta", "metadata": {"altitude_m": 99.0}})
        ws.send_bytes(shots[1][0].jpeg)
        p = ws.receive_json()
    assert p["type"] == "pose" and p["seq"] == 0 and p["altitude_m"] == 99.0


def test_initial_pose_heading(service):
    c = service.client
    sid, auth = service.new_session()
    url = f"/v1/sessions/{sid}/initial-pose"
    for body in ({"x": 0, "y": 0, "heading_deg": 360}, {"x": 0, "y": 0, "heading_deg": -5},
                 {"x": 0, "y": 0, "heading_sigma_deg": 5}):
        r = c.post(url, json=body, headers=auth)
        assert r.status_code == 422 and "heading" in r.text, body
    # the particle filter keeps positions only: it says so rather than drop the heading
    r = c.post(url, json={"x": 0, "y": 0, "heading_deg": 90, "heading_sigma_deg": 10},
               headers=auth)
    assert r.status_code == 422 and r.json()["type"].endswith("bad-control")
    assert "heading_deg" in r.json()["detail"]
    assert c.post(url, json={"x": 0, "y": 0}, headers=auth).status_code == 200
