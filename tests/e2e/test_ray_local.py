"""``VLOC_ENGINE=ray`` with its default settings and no ``VLOC_RAY_ADDRESS``, beside
another deployment's Ray cluster on the same machine: the server starts a private cluster
(it never joins the other one, nor uses shards it finds there), and the whole flow runs on
this 2-CPU machine although the shards reserve a CPU each: upload (image checks), build,
session, frames."""

from __future__ import annotations

import asyncio
import os

import httpx
import pytest

from tests.app.imagery import map_and_queries
from tests.e2e.conftest import start_server
from tests.e2e.test_server import _build_map

ray = pytest.importorskip("ray")


def test_the_whole_flow_on_a_private_cluster_with_default_settings(ray_cluster, tmp_path):
    # ``ray_cluster`` is the other deployment: a cluster this machine already runs, which
    # Ray's default (no address) would join.
    assert not {"VLOC_RAY_ADDRESS", "VLOC_RAY_SHARD_CPUS", "RAY_ADDRESS"} & set(os.environ)
    env = {"VLOC_ENGINE": "ray", "VLOC_WORKERS": "2"}
    server = start_server(tmp_path / "data", env=env, timeout=180)
    try:
        maps, queries = map_and_queries(6)

        async def scenario() -> list[int]:
            admin = {"Authorization": f"Bearer {server.admin_key()}"}
            async with httpx.AsyncClient(base_url=server.base_url, headers=admin,
                                         timeout=120) as http:
                map_id = await _build_map(http, maps)
                r = await http.post("/v1/sessions", json={
                    "map_id": map_id, "params": {"n_particles": 60}, "seed": 2})
                assert r.status_code == 201, r.text
                sid, token = r.json()["id"], r.json()["token"]
                bearer = {"Authorization": f"Bearer {token}", "Content-Type": "image/jpeg"}
                codes = []
                for q in queries[:3]:
                    r = await http.post(f"/v1/sessions/{sid}/frames", content=q.jpeg,
                                        headers=bearer, params={"wait": "true"})
                    codes.append(r.status_code)
                return codes

        assert asyncio.run(scenario()) == [200, 200, 200]
        # nothing of this server's in the other cluster
        with pytest.raises(ValueError):
            ray.get_actor("vloc-shard-0", namespace="vloc")
    finally:
        server.stop()
    assert '"msg": "vloc stopped"' in server.stderr_path.read_text()
