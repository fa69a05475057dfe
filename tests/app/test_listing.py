"""Pagination, the coverage query and the enums of the schema, against the real app."""

from __future__ import annotations

import pytest

from tests.app.conftest import ADMIN, PROBLEM
from vloc.app.maps.coverage import haversine_m


def test_maps_and_sessions_page(service):
    c = service.client
    ids = [c.post("/v1/maps", json={"name": f"page {i}"}, headers=ADMIN).json()["id"]
           for i in range(3)]
    every = [m["id"] for m in c.get("/v1/maps", headers=ADMIN).json()]
    assert set(ids) <= set(every)
    assert len(c.get("/v1/maps", params={"limit": 1}, headers=ADMIN).json()) == 1
    pages = [m["id"] for off in range(len(every)) for m in
             c.get("/v1/maps", params={"limit": 1, "offset": off}, headers=ADMIN).json()]
    assert pages == every
    assert c.get("/v1/maps", params={"offset": len(every)}, headers=ADMIN).json() == []
    for sid in ids:
        assert c.delete(f"/v1/maps/{sid}", headers=ADMIN).status_code == 204
    service.new_session()
    service.new_session()
    sessions = [s["id"] for s in c.get("/v1/sessions", headers=ADMIN).json()]
    assert [s["id"] for s in c.get("/v1/sessions", params={"limit": 1, "offset": 1},
                                   headers=ADMIN).json()] == sessions[1:2]


def test_images_page_by_id(service):
    c = service.client
    url = f"/v1/maps/{service.map_id}/images"
    every = [i["id"] for i in c.get(url, headers=ADMIN).json()]
    assert len(every) == 10 and every == sorted(every)
    first = c.get(url, params={"limit": 4}, headers=ADMIN).json()
    second = c.get(url, params={"limit": 4, "after_id": first[-1]["id"]}, headers=ADMIN).json()
    assert [i["id"] for i in first + second] == every[:8]


@pytest.mark.parametrize("params", [{"limit": 0}, {"limit": 100000}, {"offset": -1}])
def test_bad_pages_are_422(service, params):
    r = service.client.get("/v1/maps", params=params, headers=ADMIN)
    assert r.status_code == 422 and r.headers["content-type"] == PROBLEM


def test_coverage(service):
    c = service.client
    images = c.get(f"/v1/maps/{service.map_id}/images", headers=ADMIN).json()
    target = images[3]
    found = c.get("/v1/maps/coverage", params={"lat": target["lat"], "lon": target["lon"]},
                  headers=ADMIN).json()
    mine = [f for f in found if f["map_id"] == service.map_id]
    assert len(mine) == 1 and mine[0]["distance_m"] == pytest.approx(0.0, abs=1e-6)
    near = [i for i in images
            if haversine_m(target["lat"], target["lon"], i["lat"], i["lon"]) <= 50.0]
    assert mine[0]["image_count"] == len(near)
    # 1 km north of every image: not covered within 50 m, covered within 5 km
    far_lat = max(i["lat"] for i in images) + 1000.0 / 111_195.0
    assert service.map_id not in [f["map_id"] for f in c.get(
        "/v1/maps/coverage", params={"lat": far_lat, "lon": target["lon"]},
        headers=ADMIN).json()]
    wide = c.get("/v1/maps/coverage", params={"lat": far_lat, "lon": target["lon"],
                                              "radius_m": 5000}, headers=ADMIN).json()
    assert service.map_id in [f["map_id"] for f in wide]
    d = next(f["distance_m"] for f in wide if f["map_id"] == service.map_id)
    assert 990.0 < d < 1010.0
    assert c.get("/v1/maps/coverage", params={"lat": 91, "lon": 0},
                 headers=ADMIN).status_code == 422
    assert c.get("/v1/maps/coverage", params={"lat": 0, "lon": 0}).status_code == 401


def test_haversine_known_distance():
    # one degree of latitude on the mean sphere
    assert haversine_m(0.0, 0.0, 1.0, 0.0) == pytest.approx(111_195.08, abs=0.01)


def test_states_and_modes_are_enums_in_the_schema(service):
    schemas = service.client.get("/openapi.json").json()["components"]["schemas"]
    assert schemas["MapRead"]["properties"]["status"]["enum"] == [
        "empty", "unbuilt", "building", "ready", "failed"]
    assert set(schemas["JobRead"]["properties"]["status"]["enum"]) == {
        "queued", "running", "done", "failed"}
    assert set(schemas["SessionRead"]["properties"]["mode"]["enum"]) == {
        "hybrid", "global", "sift", "hierarchical", "retrieval"}
    assert set(schemas["SessionRead"]["properties"]["state"]["enum"]) == {"active", "expired"}
    status = schemas["PoseEstimate"]["properties"]["status"]
    ref = status.get("$ref", "").rsplit("/", 1)[-1]
    assert set((schemas[ref] if ref else status)["enum"]) == {
        "initialising", "tracking", "lost"}


def test_every_route_is_described(service):
    paths = service.client.get("/openapi.json").json()["paths"]
    bare = [f"{m.upper()} {p}" for p, ops in paths.items() for m, op in ops.items()
            if not op.get("description")]
    assert bare == []


def test_a_rebuild_with_nothing_new_is_409_unless_forced(service):
    from tests.app.conftest import wait_job

    c = service.client
    revision = c.get(f"/v1/maps/{service.map_id}", headers=ADMIN).json()["revision"]
    r = c.post(f"/v1/maps/{service.map_id}/build", headers=ADMIN)
    assert r.status_code == 409 and r.json()["type"].endswith("map-up-to-date")
    assert r.json()["revision"] == revision
    assert c.get(f"/v1/maps/{service.map_id}", headers=ADMIN).json()["revision"] == revision
    forced = c.post(f"/v1/maps/{service.map_id}/build", params={"force": "true"},
                    headers=ADMIN)
    assert forced.status_code == 202
    job = wait_job(c, forced.json()["job_id"])
    assert (job["status"], job["revision"], job["n_images"]) == ("done", revision + 1, 0)
