"""The local process-pool engine, with test-only tasks and a counting localiser."""

from __future__ import annotations

import os
import queue
import signal

import pytest

from tests.engine import fakes
from tests.engine.fakes import COUNTING, counting_spec, grey_png
from vloc.workers.engine import (
    Checkpoint,
    Engine,
    FrameDone,
    FrameFailed,
    LocalEngine,
    SessionSpec,
    WorkerDied,
)

TIMEOUT = 60


@pytest.fixture
def outcomes() -> queue.Queue:
    return queue.Queue()


@pytest.fixture
def engine(outcomes):
    eng = LocalEngine(2, on_outcome=outcomes.put)
    eng.start()
    yield eng
    eng.close()


def _take(outcomes: queue.Queue, n: int) -> list:
    return [outcomes.get(timeout=TIMEOUT) for _ in range(n)]


def test_call_runs_in_a_worker_process_and_returns_its_value(engine):
    assert engine.call("tests.engine.fakes:square", 7).result(TIMEOUT) == 49
    pid = engine.call("tests.engine.fakes:pid").result(TIMEOUT)
    assert pid in engine.worker_pids() and pid != os.getpid()


def test_a_function_passed_by_reference_runs_in_a_worker(engine):
    assert isinstance(engine, Engine) and not engine.shared
    assert engine.call(fakes.square, 8).result(TIMEOUT) == 64
    assert engine.call(fakes.pid).result(TIMEOUT) in engine.worker_pids()


def test_call_error_comes_back_as_the_builtin_type(engine):
    with pytest.raises(ValueError, match="no good"):
        engine.call("tests.engine.fakes:fail", "no good").result(TIMEOUT)
    # The worker survives its task's exception.
    assert engine.call("tests.engine.fakes:square", 3).result(TIMEOUT) == 9


def test_a_call_its_caller_cancelled_leaves_the_engine_working(engine, outcomes, tmp_path):
    """A caller that stops waiting (a timeout, a request that went away) cancels its
    future; the worker's late answer to it is dropped, and everything else still comes
    back."""
    release = tmp_path / "release"
    held = [engine.call("tests.engine.fakes:wait_for_file", str(release)) for _ in range(2)]
    assert all(fut.cancel() for fut in held)
    release.touch()
    engine.open_session(counting_spec("a")).result(TIMEOUT)
    engine.submit_frame("a", 0, grey_png(10))
    assert isinstance(_take(outcomes, 1)[0], FrameDone)
    assert engine.call("tests.engine.fakes:square", 4).result(TIMEOUT) == 16


def test_frames_of_a_session_come_back_in_order(engine, outcomes):
    engine.open_session(counting_spec("a")).result(TIMEOUT)
    engine.open_session(counting_spec("b", offset=100)).result(TIMEOUT)
    # Least-busy pinning puts the second session on the other worker.
    assert {engine.worker_index("a"), engine.worker_index("b")} == {0, 1}
    for seq in range(5):
        engine.submit_frame("a", seq, grey_png(10 * seq))
        engine.submit_frame("b", seq, grey_png(20))
    got = _take(outcomes, 10)
    a = [o for o in got if o.session_id == "a"]
    b = [o for o in got if o.session_id == "b"]
    assert [o.seq for o in a] == list(range(5)) and [o.seq for o in b] == list(range(5))
    assert [o.estimate.x for o in a] == [1.0, 2.0, 3.0, 4.0, 5.0]
    assert [o.estimate.y for o in a] == [0.0, 10.0, 20.0, 30.0, 40.0]
    assert [o.estimate.x for o in b] == [101.0, 102.0, 103.0, 104.0, 105.0]
    # Each names the one answered before it, for viewers that hear them by several paths.
    assert [o.prev_seq for o in a] == [None, 0, 1, 2, 3]
    assert engine.pending_frames("a") == 0


def test_bad_image_and_localiser_error_fail_one_frame_only(engine, outcomes):
    engine.open_session(counting_spec("s")).result(TIMEOUT)
    engine.submit_frame("s", 1, b"\x89PNG\r\n\x1a\n garbage")
    engine.submit_frame("s", 2, grey_png(255))
    engine.submit_frame("s", 3, grey_png(5))
    bad, error, good = _take(outcomes, 3)
    assert isinstance(bad, FrameFailed) and bad.kind == "bad_image" and bad.seq == 1
    assert isinstance(error, FrameFailed) and error.kind == "error"
    assert "too bright" in error.reason
    assert isinstance(good, FrameDone) and good.seq == 3 and good.estimate.x == 1.0
    assert [o.prev_seq for o in (bad, error, good)] == [None, 1, 2]


def test_controls_run_in_order_with_frames_and_checkpoint(engine, outcomes):
    engine.open_session(counting_spec("s")).result(TIMEOUT)
    engine.submit_frame("s", 1, grey_png(1))
    engine.control("s", "set_initial_pose", x=40, y=0).result(TIMEOUT)
    engine.submit_frame("s", 2, grey_png(1))
    first, checkpoint, second = _take(outcomes, 3)
    assert (first.estimate.x, second.estimate.x) == (1.0, 41.0)
    # The control's state comes back between the frames, in the session's order.
    assert isinstance(checkpoint, Checkpoint) and checkpoint.state == (40).to_bytes(8, "little")
    assert second.state == (41).to_bytes(8, "little")
    engine.control("s", "reset").result(TIMEOUT)
    assert engine.last_state("s") == (0).to_bytes(8, "little")
    assert _take(outcomes, 1)[0].state == (0).to_bytes(8, "little")
    assert engine.control("s", "stats").result(TIMEOUT) == {"steps": 41}


def test_unknown_mode_fails_the_open_and_leaves_no_session(engine):
    spec = SessionSpec("x", "", 0, "", "nope", factory=COUNTING)
    with pytest.raises(ValueError, match="unknown mode"):
        engine.open_session(spec).result(TIMEOUT)
    assert not engine.is_open("x")
    with pytest.raises(KeyError):
        engine.submit_frame("x", 1, grey_png(1))


def test_checkpoint_every_n_frames(outcomes):
    eng = LocalEngine(1, on_outcome=outcomes.put, checkpoint_every=3)
    eng.start()
    try:
        eng.open_session(counting_spec("s")).result(TIMEOUT)
        for seq in range(6):
            eng.submit_frame("s", seq, grey_png(1))
        states = [o.state for o in _take(outcomes, 6)]
        assert [s is not None for s in states] == [False, False, True, False, False, True]
    finally:
        eng.close()


def test_killed_worker_is_replaced_and_its_sessions_resume(outcomes, tmp_path):
    engine = LocalEngine(1, on_outcome=outcomes.put)
    engine.start()
    try:
        engine.open_session(counting_spec("s")).result(TIMEOUT)
        for seq in range(3):
            engine.submit_frame("s", seq, grey_png(1))
        assert [o.estimate.x for o in _take(outcomes, 3)] == [1.0, 2.0, 3.0]
        (victim,) = engine.worker_pids()
        # Hold the worker so that the next frames are certainly queued on it when it dies.
        held = engine.call("tests.engine.fakes:wait_for_file", str(tmp_path / "never"))
        engine.submit_frame("s", 3, grey_png(1))
        engine.submit_frame("s", 4, grey_png(1))
        os.kill(victim, signal.SIGKILL)
        lost = _take(outcomes, 2)
        assert [(o.seq, o.kind) for o in lost] == [(3, "worker_died"), (4, "worker_died")]
        assert str(victim) in lost[0].reason
        with pytest.raises(WorkerDied):
            held.result(TIMEOUT)
        assert engine.restarts == 1 and engine.worker_pids() != [victim]
        # The session lives on from its checkpoint after frame 2: three steps, then one more.
        engine.submit_frame("s", 5, grey_png(1))
        (after,) = _take(outcomes, 1)
        assert isinstance(after, FrameDone) and after.estimate.x == 4.0
        assert engine.alive()
    finally:
        engine.close()


def test_a_session_moved_to_another_revision_stays_there_when_its_worker_is_replaced(
        outcomes, tmp_path):
    """``move`` runs between two frames: the frames before it name revision 1, those
    after name revision 2 and go on counting; a worker that dies afterwards is replaced
    and reopens the session on revision 2 from its checkpoint."""
    from dataclasses import replace

    engine = LocalEngine(1, on_outcome=outcomes.put)
    engine.start()
    try:
        first = replace(counting_spec("s"), map_id="m", revision=1)
        engine.open_session(first).result(TIMEOUT)
        for seq in range(2):
            engine.submit_frame("s", seq, grey_png(1))
        moved = engine.control("s", "move", spec=replace(first, revision=2))
        engine.submit_frame("s", 2, grey_png(1))
        assert moved.result(TIMEOUT) == 2
        got = _take(outcomes, 4)
        frames = [o for o in got if isinstance(o, FrameDone)]
        assert [(o.seq, o.revision, o.estimate.x) for o in frames] == [
            (0, 1, 1.0), (1, 1, 2.0), (2, 2, 3.0)]
        assert [type(o) for o in got].index(Checkpoint) == 2  # between frames 1 and 2
        # moving to where it is changes nothing; a move to another map is refused
        assert engine.control("s", "move", spec=replace(first, revision=2)).result(
            TIMEOUT) == 2
        with pytest.raises(ValueError, match="own map"):
            engine.control("s", "move", spec=replace(first, map_id="n")).result(TIMEOUT)
        _take(outcomes, 1)  # the checkpoint of the move that changed nothing
        (victim,) = engine.worker_pids()
        os.kill(victim, signal.SIGKILL)
        engine.submit_frame("s", 3, grey_png(1))
        (after,) = _take(outcomes, 1)
        while isinstance(after, FrameFailed):  # sent while the worker was dying
            engine.submit_frame("s", after.seq + 1, grey_png(1))
            (after,) = _take(outcomes, 1)
        assert isinstance(after, FrameDone) and after.revision == 2
        assert after.estimate.x == 4.0
    finally:
        engine.close()


def test_closed_engine_refuses_work(outcomes):
    eng = LocalEngine(1, on_outcome=outcomes.put)
    eng.start()
    eng.close()
    from vloc.workers.engine import EngineClosed

    with pytest.raises(EngineClosed):
        eng.call("tests.engine.fakes:square", 2)


def test_a_worker_that_cannot_be_replaced_at_once_is_retried(outcomes):
    import time

    engine = LocalEngine(1, on_outcome=outcomes.put)
    engine.start()
    try:
        engine.open_session(counting_spec("s")).result(TIMEOUT)
        engine.submit_frame("s", 0, grey_png(1))
        _take(outcomes, 1)
        real, attempts = engine.supervisor._spawn, []

        def flaky(index):
            attempts.append(index)
            if len(attempts) == 1:
                raise OSError("fork refused")
            return real(index)

        engine.supervisor._spawn = flaky
        os.kill(engine.worker_pids()[0], signal.SIGKILL)
        deadline = time.monotonic() + TIMEOUT
        while engine.restarts == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert attempts == [0, 0] and engine.restarts == 1
        engine.submit_frame("s", 1, grey_png(1))
        (after,) = _take(outcomes, 1)
        assert after.estimate.x == 2.0  # resumed from the checkpoint after frame 0
    finally:
        engine.close()
