"""Route maps and navigation sessions over HTTP, on the real app and database."""

from __future__ import annotations

import math
import time
import uuid

import pytest

from tests.app.conftest import ADMIN, PROBLEM, snapshot
from tests.app.test_sessions import post_frame

TIMEOUT = 120
ROTATION = 0.6
"""The odometry frame is turned against the map's east-north frame and shifted."""
PARAMS = '{"max_length": 30, "loop_threshold": 0.95}'
"""Every 20 m image its own node; the test map's overlapping nadir crops would otherwise
close loops between neighbouring rows of the lawnmower path."""


def odometry_csv(shots, *, rows=None, extra="") -> bytes:
    """The shots in driving order as wheel odometry would see them: positions in a frame
    turned by ROTATION and moved, heading towards the next shot."""
    c, s = math.cos(ROTATION), math.sin(ROTATION)
    pts = [(c * sh.east - s * sh.north + 40.0, s * sh.east + c * sh.north - 15.0)
           for sh in shots]
    lines = ["filename,x,y,theta" + extra]
    for k, (sh, (x, y)) in enumerate(zip(shots, pts, strict=True)):
        nx, ny = pts[min(k + 1, len(pts) - 1)]
        px, py = pts[max(k - 1, 0)] if k == len(pts) - 1 else (x, y)
        theta = math.atan2(ny - py, nx - px) if k == len(pts) - 1 else math.atan2(ny - y, nx - x)
        lines.append(f"{sh.name},{x:.4f},{y:.4f},{theta:.5f}")
    if rows is not None:
        lines = lines[:1] + rows(lines[1:])
    return ("\n".join(lines) + "\n").encode()


def post_route(client, map_id, csv_bytes, **form):
    data = {"name": "taught", "max_step_m": "35", "params": PARAMS} | form
    return client.post(f"/v1/maps/{map_id}/routes", headers=ADMIN, data=data,
                       files={"odometry": ("odometry.csv", csv_bytes, "text/csv")})


def wait_route(client, map_id, route_id) -> dict:
    deadline = time.monotonic() + TIMEOUT
    while True:
        r = client.get(f"/v1/maps/{map_id}/routes/{route_id}", headers=ADMIN).json()
        if r["status"] != "building" or time.monotonic() > deadline:
            return r
        time.sleep(0.05)


@pytest.fixture(scope="module")
def route(service, shots) -> dict:
    r = post_route(service.client, service.map_id, odometry_csv(shots[0]))
    assert r.status_code == 202, r.text
    assert r.headers["location"].endswith(r.json()["id"])
    done = wait_route(service.client, service.map_id, r.json()["id"])
    assert done["status"] == "ready", done
    return done


def test_route_is_partitioned_relaxed_and_put_in_the_map_frame(service, shots, route):
    images = {i["filename"]: i for i in
              service.client.get(f"/v1/maps/{service.map_id}/images", headers=ADMIN).json()}
    assert route["n_images"] == len(shots[0]) == len(route["images"])
    assert route["n_nodes"] == len(route["nodes"]) >= 2
    assert [n["idx"] for n in route["nodes"]] == list(range(route["n_nodes"]))
    assert route["n_loops"] == 0
    assert [a["kind"] for a in route["arcs"]] == ["odometry"] * (route["n_nodes"] - 1)
    # exact odometry: once aligned, the taught path lies on the map's own image positions
    # (to the few centimetres by which the shots' flat-earth metres and the map's
    # geodetic east/north differ)
    err = [math.hypot(i["x"] - images[i["filename"]]["east"],
                      i["y"] - images[i["filename"]]["north"]) for i in route["images"]]
    assert max(err) < 0.15
    assert route["length_m"] == pytest.approx(
        sum(math.hypot(a.east - b.east, a.north - b.north)
            for a, b in zip(shots[0], shots[0][1:], strict=False)), rel=5e-3)
    # a node's pose is its first image's pose
    for node in route["nodes"]:
        first = route["images"][node["first_seq"]]
        assert (node["x"], node["y"]) == pytest.approx((first["x"], first["y"]), abs=1e-6)
    listed = service.client.get(f"/v1/maps/{service.map_id}/routes", headers=ADMIN).json()
    assert route["id"] in [r["id"] for r in listed]


def _drop_row(k):
    return lambda rows: rows[:k] + rows[k + 1:]


def _set_cell(k, col, value):
    def edit(rows):
        cells = rows[k].split(",")
        cells[col] = value
        return rows[:k] + [",".join(cells)] + rows[k + 1:]
    return edit


@pytest.mark.parametrize(("rows", "kind", "words"), [
    (_drop_row(3), "bad-odometry", "gap"),                        # an image missing
    (_set_cell(2, 1, "nan"), "bad-odometry", "finite"),
    (_set_cell(4, 3, "inf"), "bad-odometry", "finite"),
    (_set_cell(1, 2, "north"), "bad-odometry", "not a number"),
    (_set_cell(5, 0, "never_uploaded.jpg"), "unknown-images", "never_uploaded.jpg"),
    (_set_cell(5, 0, "map_000.jpg"), "bad-odometry", "already row 1"),
    (lambda rows: rows[:2], "bad-odometry", "at least 3"),
])
def test_bad_odometry_is_refused_and_changes_nothing(service, shots, route, rows, kind, words):
    c = service.client
    before = snapshot(c)
    r = post_route(c, service.map_id, odometry_csv(shots[0], rows=rows))
    assert r.status_code == 422, r.text
    assert r.headers["content-type"] == PROBLEM
    assert r.json()["type"] == f"urn:vloc:problem:{kind}"
    assert words in r.json()["detail"]
    assert snapshot(c) == before


@pytest.mark.parametrize(("csv_bytes", "form", "words"), [
    (b"filename,x,y\nmap_000.jpg,0,0\n", {}, "missing column(s) theta"),
    (b"filename,x,y,theta,speed\n", {}, "unknown column(s) speed"),
    (b"\xff\xfe\x00", {}, "UTF-8"),
    (None, {"params": '{"max_length": -1}'}, "max_length"),
    (None, {"params": '{"bogus": 1}'}, "bogus"),
    (None, {"params": "[1, 2]"}, "JSON object"),
    (None, {"max_step_m": "nan"}, "max_step_m"),
])
def test_bad_route_requests_are_refused(service, shots, route, csv_bytes, form, words):
    c = service.client
    before = snapshot(c)
    r = post_route(c, service.map_id, csv_bytes or odometry_csv(shots[0]), **form)
    assert r.status_code == 422, r.text
    assert r.headers["content-type"] == PROBLEM and words in r.text
    assert snapshot(c) == before


def test_half_given_gps_is_refused(service, shots, route):
    csv_bytes = odometry_csv(shots[0], extra=",lat,lon",
                             rows=lambda rows: [r + ",48.5," for r in rows])
    r = post_route(service.client, service.map_id, csv_bytes)
    assert r.status_code == 422 and "both lat and lon" in r.json()["detail"]


def test_route_of_an_unknown_map_or_id_is_404(service, route):
    c = service.client
    assert c.get(f"/v1/maps/{service.map_id}/routes/nope", headers=ADMIN).status_code == 404
    other = "00000000-0000-0000-0000-000000000000"
    assert c.get(f"/v1/maps/{other}/routes/{route['id']}", headers=ADMIN).status_code == 404
    assert c.get(f"/v1/maps/{service.map_id}/routes", headers={}).status_code == 401


def test_navigation_session_follows_the_route_and_arrives(service, shots, route):
    """Frames of the route's first, straight leg as a robot driving it at 20 m/s would see
    them, one a second: each pose carries the path following, and the last arrives."""
    c = service.client
    to_node = route["images"][3]["node"]
    leg = [i["seq"] for i in route["images"] if i["node"] <= to_node]
    assert 3 <= len(leg) <= 5                    # the first row of the lawnmower path
    sid, auth = service.new_session(
        mode="retrieval", params={},
        navigation={"route_id": route["id"], "to_node": to_node,
                    "params": {"arrive_tolerance": 4.0, "v_max": 20.0, "alpha": 0.05,
                               "visual": False}})
    read = c.get(f"/v1/sessions/{sid}", headers=auth).json()
    assert read["navigation"]["route_id"] == route["id"]
    assert read["navigation"]["nodes"] == [0, to_node]
    assert read["navigation"]["points"] == len(leg)
    poses = []
    for seq in leg:
        r = post_frame(c, sid, shots[0][seq].jpeg, auth, wait="true")
        assert r.status_code == 200, r.text
        poses.append(r.json())
    nav = [p["navigation"] for p in poses]
    assert set(nav[0]["state"]) == {"x", "y", "theta", "v", "omega"}
    assert set(nav[0]["command"]) == {"v", "omega"}
    progress = [n["progress"] for n in nav]
    assert progress == sorted(progress) and progress[-1] > progress[0] + 30
    assert all(n["fused"] for n in nav)
    assert not any(n["arrived"] for n in nav[:-1])
    assert nav[-1]["arrived"] and nav[-1]["command"] == {"v": 0.0, "omega": 0.0}
    assert nav[-1]["node"] == to_node
    # driving along a straight leg: the commands go straight and fast
    for n in nav[1:-1]:
        assert n["command"]["v"] == pytest.approx(20.0, rel=0.2)
        assert abs(n["command"]["omega"]) < 0.3
    # the reference point lies on the taught path, near the estimate
    for n, p in zip(nav, poses, strict=True):
        assert math.hypot(n["reference"]["x"] - p["x"], n["reference"]["y"] - p["y"]) < 5.0
        assert abs(n["cross_track"]) < 3.0
    # stored as streamed
    stored = c.get(f"/v1/sessions/{sid}/poses", headers=auth).json()
    assert [p["navigation"] for p in stored] == nav


@pytest.mark.parametrize(("navigation", "status", "words"), [
    ({"route_id": "00000000-0000-0000-0000-000000000000"}, 404, "does not exist"),
    ({"route_id": "ROUTE", "from_node": 1, "to_node": 1}, 422, "before"),
    ({"route_id": "ROUTE", "to_node": 999}, 422, "to_node"),
    ({"route_id": "ROUTE", "params": {"alpha": -1.0}}, 422, "alpha"),
    ({"route_id": "ROUTE", "params": {"alpha": "1"}}, 422, "alpha"),
    ({"route_id": "ROUTE", "params": {"speed": 1.0}}, 422, "speed"),
])
def test_bad_navigation_is_refused_and_changes_nothing(service, route, navigation, status,
                                                       words):
    c = service.client
    body = {"map_id": service.map_id, "mode": "retrieval",
            "navigation": {k: (route["id"] if v == "ROUTE" else v) for k, v in navigation.items()}}
    before = snapshot(c)
    r = c.post("/v1/sessions", headers=ADMIN, json=body)
    assert r.status_code == status, r.text
    assert r.headers["content-type"] == PROBLEM and words in r.text
    assert snapshot(c) == before


def test_deleting_a_route_keeps_the_sessions_path(service, shots):
    c = service.client
    r = post_route(c, service.map_id, odometry_csv(shots[0]))
    route = wait_route(c, service.map_id, r.json()["id"])
    sid, auth = service.new_session(mode="retrieval", params={},
                                    navigation={"route_id": route["id"]})
    assert c.delete(f"/v1/maps/{service.map_id}/routes/{route['id']}",
                    headers=ADMIN).status_code == 204
    assert c.get(f"/v1/maps/{service.map_id}/routes/{route['id']}",
                 headers=ADMIN).status_code == 404
    r = post_frame(c, sid, shots[0][0].jpeg, auth, wait="true")
    assert r.status_code == 200 and r.json()["navigation"]["progress"] >= 0.0


def test_deleting_a_map_deletes_its_routes(module_client, shots):
    from tests.app.conftest import build_map

    c = module_client
    map_id = build_map(c, shots[0][:4], name="short")
    r = post_route(c, map_id, odometry_csv(shots[0][:4]))
    route = wait_route(c, map_id, r.json()["id"])
    assert route["status"] == "ready" and route["n_images"] == 4
    assert c.delete(f"/v1/maps/{map_id}", headers=ADMIN).status_code == 204
    assert c.get(f"/v1/maps/{map_id}/routes/{route['id']}", headers=ADMIN).status_code == 404
    ctx = c.app.state.ctx
    with ctx.db_sessions() as db:
        from sqlalchemy import func, select

        from vloc.app.teach.models import Route, RouteImage

        assert db.scalar(select(func.count()).select_from(Route)
                         .where(Route.map_id == uuid.UUID(map_id))) == 0
        assert db.scalar(select(func.count()).select_from(RouteImage)
                         .where(RouteImage.route_id == uuid.UUID(route["id"]))) == 0
