"""Health, readiness, metrics, OpenAPI and the problem shape of unrouted requests."""

from __future__ import annotations

from tests.app.conftest import ADMIN, PROBLEM


def test_healthz_and_readyz(module_client):
    assert module_client.get("/healthz").json() == {"status": "ok"}
    r = module_client.get("/readyz").json()
    assert r["status"] == "ready" and r["workers"] == 1
    assert r["database"] in ("sqlite", "postgresql")


def test_readyz_fails_when_the_engine_is_down(tmp_path):
    from fastapi.testclient import TestClient

    from tests.app.conftest import service_settings
    from vloc.app.main import create_app

    app = create_app(service_settings(tmp_path / "d", f"sqlite:///{tmp_path}/x.db"))
    with TestClient(app) as c:
        app.state.ctx.engine.close()
        r = c.get("/readyz")
        assert r.status_code == 503 and r.headers["content-type"] == PROBLEM


def test_readyz_fails_while_a_worker_is_stopped(tmp_path):
    import os
    import signal
    import time

    from fastapi.testclient import TestClient

    from tests.app.conftest import service_settings
    from vloc.app.main import create_app

    app = create_app(service_settings(tmp_path / "d", f"sqlite:///{tmp_path}/x.db",
                                      worker_stall_s=1.0))

    def readiness_becomes(status: int) -> bool:
        deadline = time.monotonic() + 30
        while (r := c.get("/readyz")).status_code != status and time.monotonic() < deadline:
            time.sleep(0.05)
        return r.status_code == status

    with TestClient(app) as c:
        (pid,) = app.state.ctx.engine.worker_pids()
        assert c.get("/readyz").status_code == 200
        os.kill(pid, signal.SIGSTOP)  # the process exists, but runs nothing
        try:
            assert readiness_becomes(503)
            assert c.get("/readyz").json()["type"] == "urn:vloc:problem:not-ready"
        finally:
            os.kill(pid, signal.SIGCONT)
        assert readiness_becomes(200)


def test_metrics_count_requests_by_route_template(module_client):
    c = module_client
    for _ in range(3):
        c.get("/v1/maps/00000000-0000-0000-0000-000000000000", headers=ADMIN)
    text = c.get("/metrics", headers=ADMIN).text
    line = next(ln for ln in text.splitlines() if ln.startswith(
        'vloc_http_requests_total{method="GET",route="/v1/maps/{map_id}",status="404"}'))
    assert float(line.split()[-1]) >= 3
    assert "vloc_workers_alive 1.0" in text
    assert "vloc_frame_latency_seconds_bucket" in text
    assert "00000000-0000" not in text


def test_unknown_route_and_method_are_problems(module_client):
    r = module_client.get("/v2/nothing")
    assert r.status_code == 404 and r.headers["content-type"] == PROBLEM
    assert r.json()["detail"] == "no route GET /v2/nothing"
    r = module_client.put("/v1/maps", headers=ADMIN)
    assert r.status_code == 405 and r.headers["content-type"] == PROBLEM


def test_request_id_is_echoed(module_client):
    r = module_client.get("/healthz", headers={"X-Request-ID": "abc123"})
    assert r.headers["x-request-id"] == "abc123"
    assert len(module_client.get("/healthz").headers["x-request-id"]) == 32


def test_openapi_documents_the_routes(module_client):
    spec = module_client.get("/openapi.json").json()
    paths = spec["paths"]
    for path in ("/v1/maps", "/v1/maps/{map_id}/images", "/v1/maps/{map_id}/build",
                 "/v1/jobs/{job_id}", "/v1/sessions", "/v1/sessions/{session_id}/frames",
                 "/v1/sessions/{session_id}/reset", "/v1/sessions/{session_id}/initial-pose",
                 "/healthz", "/readyz"):
        assert path in paths, path
    frames = paths["/v1/sessions/{session_id}/frames"]["post"]
    assert set(frames["requestBody"]["content"]) == {"image/jpeg", "image/png"}
    assert {"MapCreate", "MapRead", "FilterSessionCreate", "PoseEstimate"} <= set(
        spec["components"]["schemas"])


def test_openapi_states_the_frame_and_readiness_failures(module_client):
    """Frames: a duplicate, stale or exhausted seq (409), an outcome not stored (500), the
    server stopping or a frame not recorded (503); readiness: 503. All as problems; the
    poses listing may hold frame errors."""
    spec = module_client.get("/openapi.json").json()
    paths = spec["paths"]
    frames = paths["/v1/sessions/{session_id}/frames"]["post"]["responses"]
    assert {"409", "500", "503"} <= set(frames)
    for status in ("409", "500", "503"):
        assert set(frames[status]["content"]) == {"application/problem+json"}, status
    assert "exhausted" in frames["409"]["description"]
    assert "not-stored" in frames["500"]["description"]
    ready = paths["/readyz"]["get"]["responses"]
    assert set(ready["503"]["content"]) == {"application/problem+json"}
    listed = paths["/v1/sessions/{session_id}/poses"]["get"]["responses"]["200"]
    items = listed["content"]["application/json"]["schema"]["items"]
    refs = {ref["$ref"].rsplit("/", 1)[-1] for ref in items["anyOf"]}
    assert refs == {"PoseEstimate", "FrameError"}
    seq = next(p for p in paths["/v1/sessions/{session_id}/frames"]["post"]["parameters"]
               if p["name"] == "seq")
    assert seq["schema"]["anyOf"][0]["maximum"] == 2**63 - 1


def test_docs_page_loads_its_assets_from_this_server(client):
    page = client.get("/docs")
    assert page.status_code == 200 and "swagger-ui" in page.text
    assert "cdn" not in page.text.lower() and "https://" not in page.text
    for asset in ("swagger-ui-bundle.js", "swagger-ui.css"):
        assert f"/docs/assets/{asset}" in page.text
        r = client.get(f"/docs/assets/{asset}")
        assert r.status_code == 200 and len(r.content) > 10_000
    assert client.get("/redoc").status_code == 404
