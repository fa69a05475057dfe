"""The service localises exactly as ``vloc eval`` does: seneca-uav, pass 1 as the map, pass 2
streamed as frames, hybrid mode, the same seed -> the same errors."""

from __future__ import annotations

import json
import subprocess
import sys
import time

import httpx
import numpy as np
import pytest

from tests.conftest import REPO_ROOT
from tests.e2e.conftest import start_server
from vloc.workers.core.evaluation.datasets import load_dataset, split
from vloc.workers.core.geo import GeoOrigin

pytestmark = [pytest.mark.slow, pytest.mark.dataset]

SEED = 5
SKIP = 10


def _eval(dataset) -> dict:
    out = subprocess.run(
        [sys.executable, "-m", "vloc.clients.cli", "eval", str(dataset), "--map-pass", "1",
         "--query-pass", "2", "--modes", "hybrid", "--starts", "1", "--skip", str(SKIP),
         "--seed", str(SEED), "--json"], cwd=REPO_ROOT, capture_output=True, text=True,
        check=True, timeout=1200)
    return json.loads(out.stdout)["modes"]["hybrid"]


def _service(server, map_images, query_images) -> tuple[dict, list[dict]]:
    admin = {"Authorization": f"Bearer {server.admin_key()}"}
    with httpx.Client(base_url=server.base_url, headers=admin, timeout=300) as http:
        map_id = http.post("/v1/maps", json={"name": "seneca pass 1"}).json()["id"]
        # Uploaded in capture order, the order the offline map has.
        files = [("files", (im.name, im.path.read_bytes(), "image/jpeg")) for im in map_images]
        r = http.post(f"/v1/maps/{map_id}/images", files=files)
        assert r.status_code == 201 and not r.json()["rejected"], r.text
        job_id = http.post(f"/v1/maps/{map_id}/build").json()["job_id"]
        while (job := http.get(f"/v1/jobs/{job_id}").json())["status"] not in ("done",
                                                                                "failed"):
            time.sleep(0.2)
        assert job["status"] == "done", job
        the_map = http.get(f"/v1/maps/{map_id}").json()
        r = http.post("/v1/sessions", json={"map_id": map_id, "mode": "hybrid",
                                            "params": {"config": "default"}, "seed": SEED})
        sid, token = r.json()["id"], r.json()["token"]
        poses = []
        for im in query_images:
            params = {"wait": "true"}
            if im.captured_at is not None:
                params["captured_at"] = repr(im.captured_at.timestamp())
            r = http.post(f"/v1/sessions/{sid}/frames", content=im.path.read_bytes(),
                          params=params, headers={"Authorization": f"Bearer {token}",
                                                  "Content-Type": "image/jpeg"})
            assert r.status_code == 200, r.text
            poses.append(r.json())
    return the_map, poses


def test_service_errors_match_vloc_eval(seneca_dir, tmp_path):
    offline = _eval(seneca_dir)
    ds = load_dataset(seneca_dir)
    map_images, query_images = split(ds, "pass", map_pass=1, query_pass=2)
    server = start_server(tmp_path / "data", workers=2)
    try:
        the_map, poses = _service(server, map_images, query_images)
    finally:
        server.stop()
    o = the_map["origin"]
    origin = GeoOrigin(o["lat"], o["lon"], o["alt"])
    lat = [im.truth_lat if im.truth_lat is not None else im.lat for im in query_images]
    lon = [im.truth_lon if im.truth_lon is not None else im.lon for im in query_images]
    east, north = origin.to_local(lat, lon)
    truth = np.column_stack([east, north])
    est = np.array([[p["x"], p["y"]] for p in poses])
    errors = np.linalg.norm(est - truth, axis=1)[SKIP:]
    assert [p["seq"] for p in poses] == list(range(len(query_images)))
    assert len(errors) == offline["frames"]
    assert errors.mean() == pytest.approx(offline["mean_error_m"], rel=1e-9)
    assert np.median(errors) == pytest.approx(offline["median_error_m"], rel=1e-9)
    assert (errors <= 25.0).mean() == pytest.approx(offline["within_25m"], abs=1e-12)
    sift_share = np.mean([p["feature"] == "sift" for p in poses])
    assert sift_share == pytest.approx(offline["sift_step_share"], abs=1e-12)
