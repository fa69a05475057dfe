"""Workers die with the process that owns the engine, and a stopped worker is not alive."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from tests.conftest import REPO_ROOT
from tests.procs import descendants, running, wait_gone
from vloc.workers.engine import LocalEngine

TIMEOUT = 30.0

# The owner of an engine: starts two workers, stops on request in the middle of sending a
# task larger than a pipe holds, and waits to be killed.
OWNER = """
import fcntl, sys, termios, time
from tests.engine.fakes import counting_spec
from vloc.workers.engine import LocalEngine

engine = LocalEngine(2, stall_s=2.0)
engine.start()
engine.open_session(counting_spec("s")).result(60)
print(*engine.worker_pids(), flush=True)
sys.stdin.readline()  # the test has stopped the session's worker
engine.submit_frame("s", 0, b"x" * 2**21)
slot = engine._slots[engine.worker_index("s")]
fd = slot.tasks._writer.fileno()
held = bytearray(4)
while True:  # until the pipe is full: the task is then written in part only
    fcntl.ioctl(fd, termios.FIONREAD, held)
    if int.from_bytes(held, sys.byteorder) >= 60_000:
        break
    time.sleep(0.01)
print("half-written", flush=True)
sys.stdin.readline()
"""


def test_workers_forkserver_and_tracker_exit_when_the_owner_is_killed():
    owner = subprocess.Popen([sys.executable, "-c", OWNER], cwd=REPO_ROOT, text=True,
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE)
    workers: set[int] = set()
    try:
        workers = {int(p) for p in owner.stdout.readline().split()}
        below = descendants(owner.pid)
        # Two workers, their forkserver and the resource tracker.
        assert len(workers) == 2 and workers < below and len(below) == 4
        for pid in workers:
            os.kill(pid, signal.SIGSTOP)
        owner.stdin.write("go\n")
        owner.stdin.flush()
        assert owner.stdout.readline().strip() == "half-written"
        owner.kill()
        owner.wait(TIMEOUT)
        for pid in workers:
            os.kill(pid, signal.SIGCONT)
        # The session's worker finds half a task in its queue: it must not wait for the rest.
        assert wait_gone(below) == set()
    finally:
        if owner.poll() is None:
            owner.kill()
        for pid in workers:
            if running(pid):
                os.kill(pid, signal.SIGKILL)


def test_a_stopped_worker_is_not_alive_until_it_runs_again():
    engine = LocalEngine(1, stall_s=1.0)
    engine.start()
    (pid,) = engine.worker_pids()
    try:
        assert engine.alive()
        os.kill(pid, signal.SIGSTOP)
        deadline = time.monotonic() + TIMEOUT
        while engine.alive() and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not engine.alive() and engine.alive_count() == 1
        os.kill(pid, signal.SIGCONT)
        while not engine.alive() and time.monotonic() < deadline:
            time.sleep(0.05)
        assert engine.alive()
        assert engine.call("tests.engine.fakes:square", 4).result(TIMEOUT) == 16
    finally:
        os.kill(pid, signal.SIGCONT)
        engine.close()


def test_stall_limit_must_exceed_the_heartbeat():
    with pytest.raises(ValueError, match="heartbeat"):
        LocalEngine(1, stall_s=0.1)
