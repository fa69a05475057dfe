"""The worker's task handling, in process: maps shared per revision, controls, errors."""

from __future__ import annotations

import numpy as np
import pytest

from vloc.workers.core.geo import GeoOrigin
from vloc.workers.core.mapdata import MapData
from vloc.workers.core.sift import SiftFeatures
from vloc.workers.engine.messages import (
    CallDone,
    CallTask,
    CloseSession,
    ControlTask,
    FrameFailed,
    FrameTask,
    OpenSession,
    SessionSpec,
)
from vloc.workers.engine.worker import WorkerState, resolve


def _map(folder, revision: int) -> str:
    rng = np.random.default_rng(revision)
    n = 4
    MapData.from_parts(
        origin=GeoOrigin(41.0, -83.0, 0.0), names=[f"m{i}" for i in range(n)],
        positions=rng.normal(size=(n, 2)) * 10, altitudes=np.zeros(n),
        global_features={"wgoh": rng.random((n, 8)).astype(np.float32)},
        sift=[SiftFeatures.empty() for _ in range(n)], map_id="m", revision=revision,
    ).save(folder)
    return str(folder)


def _spec(sid: str, folder: str, revision: int) -> SessionSpec:
    return SessionSpec(sid, "m", revision, folder, "count", {}, seed=9,
                       factory="tests.engine.fakes:make_recording")


def test_sessions_share_one_memory_mapped_map_per_revision(tmp_path):
    state = WorkerState(max_pixels=10**6)
    r1, r2 = _map(tmp_path / "r1", 1), _map(tmp_path / "r2", 2)
    for i, call_id in ((0, 1), (1, 2)):
        done = state.handle(OpenSession(_spec(f"a{i}", r1, 1), None, call_id))
        assert isinstance(done, CallDone) and done.ok
    state.handle(OpenSession(_spec("b", r2, 2), None, 3))
    maps = {sid: loc.map_data for sid, (_, loc) in state.sessions.items()}
    assert maps["a0"] is maps["a1"] is state.maps[("m", 1)]
    assert maps["b"] is state.maps[("m", 2)] and maps["b"] is not maps["a0"]
    assert isinstance(maps["a0"].positions, np.memmap)
    assert not maps["a0"].positions.flags.writeable
    assert state.sessions["a0"][1].seed == 9
    # The map goes when its last session does.
    state.handle(CloseSession("a0"))
    assert ("m", 1) in state.maps
    state.handle(CloseSession("a1"))
    assert set(state.maps) == {("m", 2)}


def test_initial_pose_in_wgs84_uses_the_sessions_map_frame(tmp_path):
    state = WorkerState(max_pixels=10**6)
    folder = _map(tmp_path / "r1", 1)
    state.handle(OpenSession(_spec("s", folder, 1), None, 1))
    east, _ = GeoOrigin(41.0, -83.0, 0.0).to_local(41.0, -82.999)
    done = state.handle(ControlTask(2, "s", "set_initial_pose", {"lat": 41.0, "lon": -82.999}))
    assert done.ok and state.sessions["s"][1].count == int(float(east))
    assert done.state == int(float(east)).to_bytes(8, "little", signed=True)


def test_failures_are_answered_not_raised(tmp_path):
    state = WorkerState(max_pixels=10**6)
    assert isinstance(state.handle(FrameTask("nobody", 1, b"")), FrameFailed)
    bad = state.handle(ControlTask(1, "nobody", "reset"))
    assert not bad.ok and bad.error_type == "KeyError"
    missing = state.handle(OpenSession(_spec("s", str(tmp_path / "absent"), 1), None, 2))
    assert not missing.ok and missing.error_type in ("FileNotFoundError", "OSError")
    failed = state.handle(CallTask(3, "tests.engine.fakes:fail", ("boom",)))
    assert (failed.ok, failed.error_type, failed.error) == (False, "ValueError", "boom")
    assert state.handle(CallTask(4, "tests.engine.fakes:square", (5,))).value == 25


def test_resolve_refuses_malformed_references():
    assert resolve("tests.engine.fakes:square")(3) == 9
    with pytest.raises(ValueError):
        resolve("no_colon")


def test_a_one_shot_localisation_and_the_sessions_share_the_map(tmp_path):
    """A worker loads a packed revision once, whoever asks: its sessions and the single-image
    localisation's task (:func:`workers.core.mapdata.open_map`)."""
    from vloc.workers.core.mapdata import open_map

    state = WorkerState(max_pixels=10**6)
    folder = _map(tmp_path / "r1", 1)
    assert state.handle(OpenSession(_spec("a", folder, 1), None, 1)).ok
    assert open_map(folder) is state.maps[("m", 1)]
