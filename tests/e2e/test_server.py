"""End to end: the real server process, a map built over HTTP from geotagged JPEGs, a query
sequence streamed in, every estimate read back from the WebSocket."""

from __future__ import annotations

import asyncio
import json

import httpx
from websockets.asyncio.client import connect

from tests.app.imagery import map_and_queries
from tests.app.test_maps import corrupt_png


async def _build_map(http: httpx.AsyncClient, shots) -> str:
    r = await http.post("/v1/maps", json={"name": "e2e"})
    assert r.status_code == 201, r.text
    map_id = r.json()["id"]
    files = [("files", (s.name, s.jpeg, "image/jpeg")) for s in shots]
    r = await http.post(f"/v1/maps/{map_id}/images", files=files)
    assert r.status_code == 201 and len(r.json()["accepted"]) == len(shots), r.text
    await _build(http, map_id)
    return map_id


async def _build(http: httpx.AsyncClient, map_id: str) -> dict:
    """Build the map and wait for the job to end; the job, done."""
    job_id = (await http.post(f"/v1/maps/{map_id}/build")).json()["job_id"]
    for _ in range(1200):
        job = (await http.get(f"/v1/jobs/{job_id}")).json()
        if job["status"] in ("done", "failed"):
            break
        await asyncio.sleep(0.1)
    assert job["status"] == "done", job
    return job


def test_map_build_and_a_streamed_sequence(server):
    maps, queries = map_and_queries(10)
    key = server.admin_key()
    # The generated key's file was announced on the first start; the key itself stays out
    # of stderr, where the logs go.
    log = server.stderr_path.read_text()
    assert key not in log and str(server.data_dir / "admin_key") in log

    async def scenario():
        admin = {"Authorization": f"Bearer {key}"}
        async with httpx.AsyncClient(base_url=server.base_url, headers=admin,
                                     timeout=60) as http:
            map_id = await _build_map(http, maps)
            r = await http.post("/v1/sessions", json={
                "map_id": map_id, "mode": "hybrid", "params": {"n_particles": 100}, "seed": 4})
            sid, token = r.json()["id"], r.json()["token"]
            frames = [(q.jpeg, "image/jpeg") for q in queries]
            frames.insert(3, (corrupt_png(), "image/png"))  # passes the header checks only
            url = f"{server.ws_url}/v1/sessions/{sid}/stream?token={token}"
            async with connect(url, max_size=2**22) as ws:
                assert json.loads(await ws.recv())["type"] == "hello"
                seqs = []
                bearer = {"Authorization": f"Bearer {token}"}
                for data, ctype in frames:
                    r = await http.post(f"/v1/sessions/{sid}/frames", content=data,
                                        headers={**bearer, "Content-Type": ctype})
                    assert r.status_code == 202, r.text
                    seqs.append(r.json()["seq"])
                # One more frame over the socket itself.
                await ws.send(queries[0].jpeg)
                got = [json.loads(await asyncio.wait_for(ws.recv(), 120))
                       for _ in range(len(frames) + 1)]
            # The stream runs ahead of the database by a few milliseconds at most.
            for _ in range(100):
                session = (await http.get(f"/v1/sessions/{sid}")).json()
                if session["frames_pending"] == 0:
                    break
                await asyncio.sleep(0.05)
        return seqs, got, session

    seqs, got, session = asyncio.run(scenario())
    assert seqs == list(range(len(queries) + 1))
    assert [m["seq"] for m in got] == seqs + [len(seqs)]
    kinds = [m["type"] for m in got]
    assert kinds[3] == "frame_error" and got[3]["kind"] == "bad_image"
    assert kinds.count("pose") == len(got) - 1
    for m in got:
        if m["type"] == "pose":
            assert {"x", "y", "lat", "lon", "sigma_x", "sigma_y", "cov", "feature", "status",
                    "latency_ms", "captured_at"} <= set(m)
    assert (session["frames_processed"], session["frames_failed"]) == (len(got) - 1, 1)
    # SIGTERM stops the server cleanly (uvicorn re-raises the signal once it has shut down).
    assert server.stop() in (0, -15)
    log = server.stderr_path.read_text()
    assert '"msg": "vloc stopped"' in log and "Traceback" not in log
