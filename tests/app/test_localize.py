"""POST /v1/maps/{id}/localize: one image, answered at once, against the real app."""

from __future__ import annotations

import math

import pytest

from tests.app.conftest import ADMIN, PROBLEM, snapshot
from tests.app.imagery import png
from vloc.workers.core.accuracy import horizontal_accuracy

JPEG = {**ADMIN, "Content-Type": "image/jpeg"}


def _localize(c, map_id, data, headers=JPEG, **params):
    return c.post(f"/v1/maps/{map_id}/localize", content=data, headers=headers, params=params)


def _distance_m(a_lat, a_lon, b_lat, b_lon) -> float:
    north = (a_lat - b_lat) * 111_320.0
    east = (a_lon - b_lon) * 111_320.0 * math.cos(math.radians(a_lat))
    return math.hypot(east, north)


def test_one_image_is_localised_near_where_it_was_taken(service, shots):
    c = service.client
    before = snapshot(c)
    q = shots[1][4]
    r = _localize(c, service.map_id, q.jpeg, captured_at=q.captured_at.isoformat())
    assert r.status_code == 200, r.text
    p = r.json()
    assert p["type"] == "localization" and p["map_id"] == service.map_id
    assert p["captured_at"].startswith(q.captured_at.strftime("%Y-%m-%dT%H:%M:%S"))
    assert p["horizontal_accuracy_m"] == pytest.approx(horizontal_accuracy(p["cov"]))
    assert p["feature"] == "sift" and p["image_filename"] is not None
    assert _distance_m(p["lat"], p["lon"], q.lat, q.lon) < 3 * p["horizontal_accuracy_m"] + 5
    assert p["latency_ms"] >= p["processing_ms"] + p["decode_ms"]
    assert snapshot(c) == before  # nothing stored


def test_a_prior_starts_the_filter_around_it(service, shots):
    c = service.client
    q = shots[1][4]
    far = _localize(c, service.map_id, q.jpeg, prior_lat=q.lat, prior_lon=q.lon,
                    prior_sigma_m=2.0)
    assert far.status_code == 200, far.text
    p = far.json()
    # particles drawn within a few metres of the prior: the spread says so
    assert p["horizontal_accuracy_m"] < 10.0
    assert _distance_m(p["lat"], p["lon"], q.lat, q.lon) < 10.0


@pytest.mark.parametrize(("params", "kind", "status"), [
    ({"prior_lat": 41.0}, "bad-prior", 422),
    ({"prior_sigma_m": 5}, "bad-prior", 422),
    ({"prior_lat": 10.0, "prior_lon": 10.0}, "bad-initial-pose", 422),
    ({"prior_lat": 41.0, "prior_lon": -83.0, "prior_sigma_m": 0}, "validation", 422),
    ({"heading_deg": 400}, "bad-metadata", 422),
    ({"mode": "retrieval"}, "validation", 422),
])
def test_bad_priors_are_422(service, shots, params, kind, status):
    r = _localize(service.client, service.map_id, shots[1][0].jpeg, **params)
    assert r.status_code == status and r.headers["content-type"] == PROBLEM
    assert r.json()["type"].endswith(kind)


def test_bad_images_and_maps(service, shots):
    c = service.client
    assert _localize(c, service.map_id, png(), headers=JPEG).status_code == 415  # declared JPEG
    assert _localize(c, service.map_id, b"GIF89a..", headers={
        **ADMIN, "Content-Type": "image/gif"}).status_code == 415
    assert _localize(c, service.map_id, shots[1][0].jpeg[:3000]).status_code == 422
    r = _localize(c, "00000000-0000-0000-0000-000000000000", shots[1][0].jpeg)
    assert r.status_code == 404
    empty = c.post("/v1/maps", json={"name": "empty"}, headers=ADMIN).json()["id"]
    r = _localize(c, empty, shots[1][0].jpeg)
    assert r.status_code == 409 and r.json()["type"].endswith("map-not-built")
    r = c.post(f"/v1/maps/{service.map_id}/localize", content=shots[1][0].jpeg,
               headers={"Content-Type": "image/jpeg"})
    assert r.status_code == 401
