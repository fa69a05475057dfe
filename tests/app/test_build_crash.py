"""A worker that dies in the middle of a pair's tie points (COLMAP can end the process on a
pair's matches) leaves that pair out; the build goes on and the rest is a clean build's."""

from __future__ import annotations

import os
import signal
import threading
import time

from tests.app.conftest import ADMIN, jpeg_files, wait_job
from vloc.app.maps.revisions import revision_images
from vloc.workers.core import tiepairs


def test_a_pair_whose_worker_dies_is_left_out_and_the_build_goes_on(module_client, shots,
                                                                     built_map):
    c = module_client
    ctx = c.app.state.ctx
    map_id = c.post("/v1/maps", json={"name": "crash"}, headers=ADMIN).json()["id"]
    c.post(f"/v1/maps/{map_id}/images", files=jpeg_files(shots[0]), headers=ADMIN)
    ids = [i["id"] for i in c.get(f"/v1/maps/{map_id}/images", headers=ADMIN).json()]
    store = ctx.settings.tie_store_dir(map_id)
    victim = f"{ids[0]} {ids[1]}"
    left: list[str] = []
    stop = threading.Event()

    def kill_while_matching_the_victim():
        # The batch records the pair it is matching before it matches it: freeze the
        # worker when that is the victim, read which pair it is in, and end it there.
        while not stop.is_set():
            for marker in store.glob("*.matching"):
                try:
                    text = marker.read_text()
                except OSError:
                    continue
                if text == victim:
                    (pid,) = ctx.engine.worker_pids()
                    os.kill(pid, signal.SIGSTOP)
                    left.append(marker.read_text())
                    os.kill(pid, signal.SIGKILL)
                    return
            time.sleep(0.001)

    watcher = threading.Thread(target=kill_while_matching_the_victim, daemon=True)
    watcher.start()
    try:
        job = wait_job(c, c.post(f"/v1/maps/{map_id}/build", headers=ADMIN).json()["job_id"],
                       timeout=300)
    finally:
        stop.set()
        watcher.join(5)
    assert job["status"] == "done", job["error"]
    assert len(left) == 1 and ctx.engine.restarts >= 1
    # the pair its worker died in is stored as tried without verifying: no build matches it
    # again, and every other pair is what a build without the crash matched
    a, b = (ids.index(int(v)) for v in left[0].split())
    found = tiepairs.load_results(store, ids)
    assert (a, b) in found and found[(a, b)] is None
    clean_ids = list(revision_images(str(built_map.data_dir / "maps" / built_map.map_id
                                          / "rev-000001")).ids)
    clean = tiepairs.load_results(built_map.data_dir / "maps" / built_map.map_id / "ties",
                                  clean_ids)
    assert set(found) == set(clean)
    for pair, matched in clean.items():
        if pair == (a, b):
            continue
        assert (found[pair] is None) == (matched is None), pair
        if matched is not None:
            assert found[pair].matches.tolist() == matched.matches.tolist()
    assert not list(store.glob("*.matching"))
    # the map was packed from them
    m = c.get(f"/v1/maps/{map_id}", headers=ADMIN).json()
    assert (m["status"], m["revision"]) == ("ready", 1)
