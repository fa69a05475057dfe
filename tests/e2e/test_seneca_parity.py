"""The service localises exactly as ``vloc eval`` does: seneca-uav, pass 1 as the map, pass 2
streamed as frames, hybrid mode, the same seed -> the same errors, whether the frames come as
plain HTTP requests or from ``vloc replay``.

Building the map is most of the cost (the frames take a few seconds), so the module builds
it twice, not four times, and both at once: offline by ``vloc eval`` and by the service, whose
map both of the service's paths then use. It flies the first half of the survey (pass 1's
first 40 images, the 48 frames of pass 2 over them) at about 60 % of a build's cost, with the
geometry accepted as on the whole survey (the hybrid from one start: 7.2 m mean, 3.5 m median,
SIFT on 42 % of steps; the whole survey's five starts: 5.1 m, 2.7 m, 31 %)."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
from click.testing import CliRunner

from tests.conftest import REPO_ROOT
from tests.e2e.conftest import start_server
from vloc.clients.cli import main as cli
from vloc.workers.core.evaluation.datasets import load_dataset, split
from vloc.workers.core.geo import GeoOrigin

pytestmark = [pytest.mark.slow, pytest.mark.dataset]

SEED = 5
SKIP = 10
FIGURES = ("mean_error_m", "median_error_m", "sift_step_share", "within_25m")
MAP_IMAGES, QUERY_FRAMES = 40, 48
"""The first half of the survey: pass 1's first 40 images, and the first 48 of pass 2, which
fly over them."""


@pytest.fixture(scope="module")
def survey(seneca_dir, tmp_path_factory) -> Path:
    """The first half of seneca-uav as a data set of its own: its images linked, its rows of
    the positions CSV copied."""
    folder = tmp_path_factory.mktemp("seneca-half")
    (folder / "images").mkdir()
    with (seneca_dir / "ground_truth.csv").open(newline="") as fh:
        reader = csv.DictReader(fh)
        rows, columns = list(reader), reader.fieldnames
    keep = ([r for r in rows if r["pass"] == "1"][:MAP_IMAGES]
            + [r for r in rows if r["pass"] == "2"][:QUERY_FRAMES])
    with (folder / "ground_truth.csv").open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=columns)
        writer.writeheader()
        writer.writerows(keep)
    for r in keep:
        (folder / "images" / r["filename"]).symlink_to(
            (seneca_dir / "images" / r["filename"]).resolve())
    return folder


@pytest.fixture(scope="module")
def offline_run(survey) -> Iterator[subprocess.Popen]:
    """``vloc eval`` on the survey, started first: it runs while the service builds."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "vloc.clients.cli", "eval", str(survey), "--map-pass", "1",
         "--query-pass", "2", "--modes", "hybrid", "--starts", "1", "--skip", str(SKIP),
         "--seed", str(SEED), "--json"], cwd=REPO_ROOT, stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True)
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


@pytest.fixture(scope="module")
def offline(offline_run) -> dict:
    out, err = offline_run.communicate(timeout=1200)
    assert offline_run.returncode == 0, err[-3000:]
    return json.loads(out)["modes"]["hybrid"]


@pytest.fixture(scope="module")
def served(offline_run, survey, tmp_path_factory):
    """A two-worker ``vloc serve`` with the survey's pass 1 map built through its API (while
    ``vloc eval`` builds its own), the map's record and the poses of pass 2 posted to it
    frame by frame."""
    ds = load_dataset(survey)
    map_images, query_images = split(ds, "pass", map_pass=1, query_pass=2)
    assert (len(map_images), len(query_images)) == (MAP_IMAGES, QUERY_FRAMES)
    server = start_server(tmp_path_factory.mktemp("seneca") / "data", workers=2)
    try:
        the_map, poses = _service(server, map_images, query_images)
        yield server, the_map, poses, query_images
    finally:
        server.stop()


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


def test_service_errors_match_vloc_eval(served, offline):
    _, the_map, poses, query_images = served
    # the half survey keeps what makes the hybrid the hybrid: a geometry frames' fixes use
    assert the_map["geometry"]["status"] == "accepted", the_map["geometry"]
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


def test_vloc_replay_on_the_served_map_matches_vloc_eval(served, offline, survey):
    server, the_map, _, query_images = served
    result = CliRunner().invoke(cli, [
        "replay", str(survey), "--server", server.base_url, "--admin-key",
        server.admin_key(), "--map-id", the_map["id"], "--map-pass", "1", "--query-pass", "2",
        "--mode", "hybrid", "--seed", str(SEED), "--skip", str(SKIP), "--json", "--quiet"])
    assert result.exit_code == 0, result.output
    got = json.loads(result.stdout)
    assert got["query_frames"] == len(query_images)
    assert got["modes"]["hybrid"]["frames_answered"] == len(query_images)
    for key in FIGURES:
        assert got["modes"]["hybrid"][key] == pytest.approx(offline[key], abs=1e-6), key
