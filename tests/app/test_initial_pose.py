"""``POST /v1/sessions/{id}/initial-pose`` at the edge: finite, within the map's extent plus
a margin, a bounded sigma; anything else is 422 and the filter is left as it was."""

from __future__ import annotations

import pytest

from tests.app.conftest import ADMIN, PROBLEM, snapshot
from tests.app.test_sessions import post_frame
from vloc.app.sessions.service import INITIAL_POSE_MARGIN_M


def _extent(service) -> dict:
    return service.client.get(f"/v1/maps/{service.map_id}", headers=ADMIN) \
        .json()["local_extent"]


def _outside(service) -> list[dict]:
    e = _extent(service)
    m = INITIAL_POSE_MARGIN_M + 1.0
    return [{"x": e["max_east"] + m, "y": e["min_north"]},
            {"x": e["min_east"] - m, "y": e["max_north"]},
            {"x": e["min_east"], "y": e["min_north"] - m},
            {"lat": 48.85, "lon": 2.35}]


BAD = {
    "huge": ({"x": 1e300, "y": 1e300, "sigma": 100000}, "validation"),
    "huge-sigma": ({"x": 0.0, "y": 0.0, "sigma": 100000}, "validation"),
    "bool-sigma": ({"x": 0.0, "y": 0.0, "sigma": True}, "validation"),
    "string-x": ({"x": "0", "y": 0.0}, "validation"),
    "extra-field": ({"x": 0.0, "y": 0.0, "theta": 1.0}, "validation"),
}


def _assert_refused(service, sid, auth, body, kind):
    c = service.client
    before = snapshot(c)
    r = c.post(f"/v1/sessions/{sid}/initial-pose", headers=auth, json=body)
    assert r.status_code == 422 and r.headers["content-type"] == PROBLEM, r.text
    assert r.json()["type"] == f"urn:vloc:problem:{kind}"
    assert snapshot(c) == before


@pytest.mark.parametrize("case", sorted(BAD))
def test_out_of_range_initial_pose_is_422(service, shots, case):
    sid, auth = service.new_session()
    body, kind = BAD[case]
    _assert_refused(service, sid, auth, body, kind)
    # The filter was not touched: the next frame gives an estimate.
    r = post_frame(service.client, sid, shots[1][0].jpeg, auth, wait="true")
    assert r.status_code == 200, r.text


def test_initial_pose_outside_the_map_is_422(service, shots):
    sid, auth = service.new_session()
    for body in _outside(service):
        _assert_refused(service, sid, auth, body, "bad-initial-pose")
    r = post_frame(service.client, sid, shots[1][0].jpeg, auth, wait="true")
    assert r.status_code == 200, r.text


def test_initial_pose_within_the_margin_is_taken(service):
    sid, auth = service.new_session()
    e = _extent(service)
    inside = INITIAL_POSE_MARGIN_M - 1.0
    r = service.client.post(f"/v1/sessions/{sid}/initial-pose", headers=auth, json={
        "x": e["max_east"] + inside, "y": e["min_north"] - inside, "sigma": 1000})
    assert r.status_code == 200, r.text
