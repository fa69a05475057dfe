"""The Ray engine on a real local Ray cluster: shard actors shared by several engines (as
several API processes would share them), numbering and ordering across them, the map in
the object store, a killed shard, build calls as Ray tasks."""

from __future__ import annotations

import os
import queue
import signal
import time
import uuid

import numpy as np
import pytest

from tests.engine import fakes
from tests.engine.fakes import COUNTING, counting_spec, grey_png
from vloc.workers.core.geo import GeoOrigin
from vloc.workers.core.mapdata import MapData
from vloc.workers.core.sift import SiftFeatures
from vloc.workers.engine import (
    Checkpoint,
    Engine,
    FrameDone,
    FrameFailed,
    SeqRefused,
    SessionSpec,
    SharedEngine,
    WorkerDied,
)

ray = pytest.importorskip("ray")

from vloc.workers.engine.ray_engine import RayEngine, shard_of  # noqa: E402

TIMEOUT = 60


def _take(outcomes: queue.Queue, n: int) -> list:
    return [outcomes.get(timeout=TIMEOUT) for _ in range(n)]


@pytest.fixture(scope="module")
def engines(ray_cluster):
    """Two engines on one namespace of the shared cluster, as two API processes would be,
    each with its outcome queue; the namespace's actors go at the end. Every test uses
    session ids of its own."""
    namespace = f"vloc-test-{uuid.uuid4().hex[:8]}"
    made = []
    for _ in range(2):
        outcomes: queue.Queue = queue.Queue()
        engine = RayEngine(2, on_outcome=outcomes.put, shard_cpus=0.25, namespace=namespace,
                           checkpoint_every=2, hold_s=1.5)
        engine.start(timeout=TIMEOUT)
        made.append((engine, outcomes))
    yield made
    for engine, _ in made:
        engine.close()
    made[0][0].remove_actors()


@pytest.fixture
def cluster(engines):
    """The engines, with nothing left in their queues from an earlier test."""
    for _, outcomes in engines:
        while not outcomes.empty():
            outcomes.get_nowait()
    return engines


def _session_on(shard: int, prefix: str) -> str:
    return next(sid for sid in (f"{prefix}-{i}" for i in range(100)) if shard_of(sid, 2) == shard)


def test_it_is_a_shared_engine_and_shards_are_found_by_name(cluster):
    (a, _), (b, _) = cluster
    assert isinstance(a, Engine) and isinstance(a, SharedEngine) and a.shared
    assert a.alive() and a.alive_count() == 2
    # Both engines reach the very same actors.
    assert [h._actor_id for h in a._shards] == [h._actor_id for h in b._shards]
    assert shard_of("s-1", 2) == shard_of("s-1", 2) and {shard_of(f"s-{i}", 2)
                                                          for i in range(20)} == {0, 1}


def test_frames_sent_through_two_engines_are_numbered_and_stepped_in_order(cluster):
    (a, out_a), (b, out_b) = cluster
    assert a.open_session(counting_spec("order")).result(TIMEOUT) == "opened"
    # The second process finds the session open and leaves its localiser alone.
    assert b.open_session(counting_spec("order", offset=100)).result(TIMEOUT) == "kept"
    seqs = [(a if i % 2 == 0 else b).reserve_seq("order", None).result(TIMEOUT)
            for i in range(6)]
    assert seqs == list(range(6))
    # Sent in the wrong order (the odd ones, through the other engine, first): the shard
    # holds each frame until the ones numbered before it have been stepped.
    for seq in (1, 3, 5):
        b.submit_frame("order", seq, grey_png(seq))
    for seq in (0, 2, 4):
        a.submit_frame("order", seq, grey_png(seq))
    got = _take(out_a, 3) + _take(out_b, 3)
    by_seq = {o.seq: o for o in got}
    assert all(isinstance(o, FrameDone) for o in got)
    # The counting localiser's x is its step count: frame seq k was step k + 1.
    assert [by_seq[k].estimate.x for k in range(6)] == [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]
    assert [by_seq[k].estimate.y for k in range(6)] == [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]
    assert a.pending_frames("order") == b.pending_frames("order") == 0


def test_a_frame_waiting_its_turn_longer_than_hold_s_keeps_its_place(cluster):
    # Each step takes longer than the engines' hold_s (1.5 s): frames 1 and 2 arrive while
    # frame 0 is stepping, and wait past their reservation's hold. The one that has arrived
    # is never given up: 2 still goes after 1.
    (a, out_a), (b, out_b) = cluster
    a.open_session(counting_spec("slow", step_s=1.0)).result(TIMEOUT)
    seqs = [a.reserve_seq("slow", None).result(TIMEOUT) for _ in range(3)]
    a.submit_frame("slow", seqs[0], grey_png(10))
    b.submit_frame("slow", seqs[1], grey_png(11))
    a.submit_frame("slow", seqs[2], grey_png(12))
    got = _take(out_a, 2) + _take(out_b, 1)
    assert all(isinstance(o, FrameDone) for o in got)
    # x is the step count, y the frame's grey level: frame k was step k + 1.
    assert sorted((o.estimate.x, o.estimate.y) for o in got) == [
        (1.0, 10.0), (2.0, 11.0), (3.0, 12.0)]


def test_a_frame_arriving_while_a_later_one_steps_is_refused_not_stepped_out_of_order(
        cluster):
    (a, out), _ = cluster
    a.open_session(counting_spec("late", step_s=3.0)).result(TIMEOUT)
    s0, s1, s2 = (a.reserve_seq("late", None).result(TIMEOUT) for _ in range(3))
    a.release_seq("late", s0)
    a.submit_frame("late", s2, grey_png(2))  # given its turn once 1's hold (1.5 s) is over
    time.sleep(2.5)  # 2 is stepping now (from 1.5 s to 4.5 s)
    a.submit_frame("late", s1, grey_png(1))
    first, second = _take(out, 2)
    assert isinstance(first, FrameFailed) and first.seq == s1 and first.kind == "error"
    assert isinstance(second, FrameDone) and second.seq == s2 and second.estimate.x == 1.0


def test_a_seq_given_by_the_client_must_be_after_the_last_one(cluster):
    (a, _), (b, _) = cluster
    a.open_session(counting_spec("given"), last_seq=9).result(TIMEOUT)
    assert a.reserve_seq("given", None).result(TIMEOUT) == 10
    assert b.reserve_seq("given", 20).result(TIMEOUT) == 20
    with pytest.raises(SeqRefused) as dup:
        a.reserve_seq("given", 20).result(TIMEOUT)
    assert (dup.value.kind, dup.value.last_seq) == ("duplicate-seq", 20)
    with pytest.raises(SeqRefused) as stale:
        b.reserve_seq("given", 15).result(TIMEOUT)
    assert stale.value.kind == "stale-seq"
    with pytest.raises(KeyError):
        a.reserve_seq("never-opened", None).result(TIMEOUT)


def test_a_released_seq_frees_the_frames_after_it_and_a_lost_one_is_waited_for_a_while(
        cluster):
    (a, out), _ = cluster
    a.open_session(counting_spec("gap")).result(TIMEOUT)
    s0, s1, s2 = (a.reserve_seq("gap", None).result(TIMEOUT) for _ in range(3))
    a.submit_frame("gap", s2, grey_png(2))
    with pytest.raises(queue.Empty):
        out.get(timeout=0.5)  # waits for 0 and 1
    a.release_seq("gap", s0)  # its record failed: it will never come
    with pytest.raises(queue.Empty):
        out.get(timeout=0.3)  # still waits for 1
    # 1 never comes either (its API process died): given up after hold_s.
    (late,) = _take(out, 1)
    assert isinstance(late, FrameDone) and late.seq == s2 and late.estimate.x == 1.0
    # A frame whose seq was given up comes too late to take its turn: reported, not lost.
    a.submit_frame("gap", s1, grey_png(1))
    (refused,) = _take(out, 1)
    assert isinstance(refused, FrameFailed) and refused.seq == s1 and refused.kind == "error"


def test_controls_run_after_the_frames_before_them_and_leave_a_checkpoint(cluster):
    (a, out), _ = cluster
    a.open_session(counting_spec("ctl")).result(TIMEOUT)
    for _seq in range(3):
        a.submit_frame("ctl", a.reserve_seq("ctl", None).result(TIMEOUT), grey_png(1))
    a.control("ctl", "set_initial_pose", x=40, y=0).result(TIMEOUT)
    got = _take(out, 4)
    frames = [o for o in got if isinstance(o, FrameDone)]
    assert [o.estimate.x for o in frames] == [1.0, 2.0, 3.0]
    # The shard counts the session's frames for its checkpoints: every second one.
    assert [o.state is not None for o in frames] == [False, True, False]
    (checkpoint,) = [o for o in got if isinstance(o, Checkpoint)]
    assert checkpoint.state == (40).to_bytes(8, "little") == a.last_state("ctl")
    assert a.control("ctl", "stats").result(TIMEOUT) == {"steps": 3}
    with pytest.raises(ValueError, match="unknown control"):
        a.control("ctl", "dance").result(TIMEOUT)


def test_an_unknown_mode_fails_the_open(cluster):
    (a, _), _ = cluster
    with pytest.raises(ValueError, match="unknown mode"):
        a.open_session(SessionSpec("x", "", 0, "", "nope", factory=COUNTING)).result(TIMEOUT)
    assert not a.is_open("x")
    with pytest.raises(KeyError):
        a.reserve_seq("x", None).result(TIMEOUT)


def test_build_calls_run_as_ray_tasks_by_reference(cluster):
    (a, _), _ = cluster
    assert a.call(fakes.square, 9).result(TIMEOUT) == 81
    assert a.call(fakes.pid).result(TIMEOUT) != os.getpid()
    with pytest.raises(ValueError, match="no good"):
        a.call(fakes.fail, "no good").result(TIMEOUT)


def _map(folder) -> str:
    rng = np.random.default_rng(3)
    n = 5
    MapData.from_parts(
        origin=GeoOrigin(41.0, -83.0, 0.0), names=[f"m{i}" for i in range(n)],
        positions=rng.normal(size=(n, 2)) * 10, altitudes=np.zeros(n),
        global_features={"wgoh": rng.random((n, 8)).astype(np.float32)},
        sift=[SiftFeatures.empty() for _ in range(n)], map_id="m", revision=1,
    ).save(folder)
    return str(folder)


def test_the_map_goes_into_the_object_store_once_and_is_read_zero_copy(cluster, tmp_path):
    (a, _), _ = cluster
    folder = _map(tmp_path / "rev1")
    stats = {}
    for shard in (0, 1):
        sid = _session_on(shard, "map")
        a.open_session(SessionSpec(sid, "m", 1, folder, "count",
                                   factory="tests.engine.fakes:make_map_probe")).result(TIMEOUT)
        stats[shard] = a.control(sid, "stats").result(TIMEOUT)
    assert stats[0]["pid"] != stats[1]["pid"]  # two shard processes
    for s in stats.values():
        assert s["n_images"] == 5
        # A read-only view of the store's shared memory, not a copy of its own.
        assert not s["writeable"] and not s["owns_data"]
        assert "ray" in s["base"], s["base"]
    store = ray.get_actor("vloc-maps", namespace=a.namespace)
    assert ray.get(store.stats.remote())["loads"] == 1


def test_a_killed_shard_fails_its_frames_in_flight_and_the_session_reopens(cluster, tmp_path):
    (a, out), _ = cluster
    sid = _session_on(0, "kill")
    gate = tmp_path / "gate"
    gate.touch()
    spec = SessionSpec(sid, "", 0, "", "count", {"gate": str(gate)},
                       factory="tests.engine.fakes:make_gated")
    a.open_session(spec).result(TIMEOUT)
    for _ in range(4):
        a.submit_frame(sid, a.reserve_seq(sid, None).result(TIMEOUT), grey_png(1))
    done = _take(out, 4)
    checkpoint = done[-1].state  # every second frame
    assert [o.estimate.x for o in done] == [1.0, 2.0, 3.0, 4.0] and checkpoint
    pid, _, _ = ray.get(a._shards[0].ping.remote())
    restarts = a.restarts
    gate.unlink()  # the next frame blocks in its step, the one after waits for its turn
    for _ in range(2):
        a.submit_frame(sid, a.reserve_seq(sid, None).result(TIMEOUT), grey_png(1))
    stalled = a.control(sid, "stats")
    with pytest.raises(queue.Empty):
        out.get(timeout=0.5)
    os.kill(pid, signal.SIGKILL)
    lost = _take(out, 2)
    assert sorted((o.seq, o.kind) for o in lost) == [(4, "worker_died"), (5, "worker_died")]
    with pytest.raises(WorkerDied):
        stalled.result(TIMEOUT)
    gate.touch()
    # While Ray restarts the shard, calls fail as WorkerDied (the service answers 503,
    # retry); once it is back it answers again...
    deadline = time.monotonic() + TIMEOUT
    while not a.alive():
        assert time.monotonic() < deadline, "the killed shard did not come back"
        time.sleep(0.2)
    # ... empty: the session is not open there until it is reopened.
    with pytest.raises(KeyError):
        a.reserve_seq(sid, None).result(TIMEOUT)
    assert a.alive() and a.restarts == restarts + 1
    assert a.open_session(spec, state=checkpoint, last_seq=5).result(TIMEOUT) == "opened"
    seq = a.reserve_seq(sid, None).result(TIMEOUT)
    a.submit_frame(sid, seq, grey_png(1))
    (resumed,) = _take(out, 1)
    # Numbering goes on after the lost frames; the filter goes on from the checkpoint.
    assert (resumed.seq, resumed.estimate.x) == (6, 5.0)


def test_build_calls_find_room_when_the_shards_reserve_every_cpu(ray_cluster):
    """Shards that reserve every CPU the cluster has left leave build calls running
    (they reserve none; the engine keeps no more running than the cluster has CPUs)."""
    namespace = f"vloc-test-{uuid.uuid4().hex[:8]}"
    free = ray.available_resources().get("CPU", 0.0)
    engine = RayEngine(1, shard_cpus=free, namespace=namespace)
    engine.start(timeout=TIMEOUT)
    try:
        assert ray.available_resources().get("CPU", 0.0) == pytest.approx(0.0, abs=1e-6)
        futures = [engine.call(fakes.square, i) for i in range(5)]
        assert [f.result(TIMEOUT) for f in futures] == [0, 1, 4, 9, 16]
    finally:
        engine.close()
        engine.remove_actors()


def test_shards_of_another_code_version_are_refused(ray_cluster):
    from vloc.workers.engine.ray_actors import Shard
    from vloc.workers.engine.ray_engine import shard_name

    namespace = f"vloc-test-{uuid.uuid4().hex[:8]}"
    old = ray.remote(Shard).options(name=shard_name(0), namespace=namespace, num_cpus=0,
                                    lifetime="detached").remote(
        0, max_pixels=10**6, checkpoint_every=1, namespace=namespace, version="0123456789")
    ray.get(old.ping.remote())
    engine = RayEngine(1, shard_cpus=0, namespace=namespace)
    try:
        with pytest.raises(RuntimeError, match="deployment 0123456789, this server"):
            engine.start(timeout=TIMEOUT)
        assert not engine.running
    finally:
        engine.remove_actors()


def test_shards_of_another_deployment_are_refused(ray_cluster):
    namespace = f"vloc-test-{uuid.uuid4().hex[:8]}"
    theirs = RayEngine(1, shard_cpus=0, namespace=namespace, deployment="theirs")
    theirs.start(timeout=TIMEOUT)
    ours = RayEngine(1, shard_cpus=0, namespace=namespace, deployment="ours")
    try:
        with pytest.raises(RuntimeError, match=r":theirs, this server .*:ours"):
            ours.start(timeout=TIMEOUT)
        assert theirs.alive()
    finally:
        theirs.close()
        theirs.remove_actors()
