"""The test suite's profiler (``bench/test_suite_profile.py``): its reading of ``/proc``, the
kinds it gives processes, and which test file it charges a process's CPU to."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

from bench.test_suite_profile import ProcessSampler, attribute, process_kind


def _my_cpu_s() -> float:
    t = os.times()
    return t.user + t.system


def _state(pid: int) -> str:
    stat = Path(f"/proc/{pid}/stat").read_text()
    return stat[stat.rindex(")") + 2]


def test_the_sampler_sees_a_child_s_cpu_and_parent():
    before = _my_cpu_s()
    sampler = ProcessSampler(interval=0.05)
    sampler.start()
    busy = subprocess.Popen([sys.executable, "-c",
                             "import time\nt = time.process_time()\n"
                             "while time.process_time() - t < 0.6: pass\ntime.sleep(0.3)"])
    # left unreaped a while after it exits: a zombie shows no command line
    deadline = time.monotonic() + 30
    while _state(busy.pid) != "Z" and time.monotonic() < deadline:
        time.sleep(0.02)
    time.sleep(0.2)
    busy.wait(30)
    sampler.stop()
    (child,) = [p for (pid, _), p in sampler.seen.items() if pid == busy.pid]
    assert child["ppid"] == os.getpid()
    assert "time.process_time()" in child["cmd"]
    assert 0.4 <= child["cpu"] <= 1.0
    assert child["start"] <= child["last"] <= time.time()
    # this process was running before the first sample: only what it did since counts
    (me,) = [p for (pid, _), p in sampler.seen.items() if pid == os.getpid()]
    assert 0 <= me["cpu"] <= _my_cpu_s() - before + 0.02


def test_process_kinds():
    assert process_kind("/v/bin/python -u -c import sys;exec(eval(sys.stdin.readline()))") \
        == "pytest workers"
    # a test's folder is named after pytest: not a pytest worker for that
    assert process_kind("/v/bin/python -m vloc.clients.cli eval /tmp/pytest-of-root/p/x") \
        == "other vloc commands"
    assert process_kind("/v/bin/python -m vloc.clients.cli serve --port 1") == "vloc serve"
    assert process_kind("/v/bin/python -B -c from multiprocessing.forkserver import main") \
        == "worker processes"
    assert process_kind("ray::IDLE") == "Ray"
    assert process_kind("postgres: 16/main: postgres test 127.0.0.1") == "PostgreSQL"
    assert process_kind("[kworker/0:1]") == "other"


def test_a_process_is_charged_to_the_test_running_on_the_worker_that_started_it():
    t0 = 1000.0
    rows = [  # two workers, 11 and 12, each running two tests
        {"id": "tests/a.py::one", "pid": 11, "start": t0, "end": t0 + 10},
        {"id": "tests/b.py::two", "pid": 11, "start": t0 + 10, "end": t0 + 20},
        {"id": "tests/c.py::three", "pid": 12, "start": t0, "end": t0 + 20},
    ]

    def proc(ppid, start, cpu, cmd="python"):
        return {"ppid": ppid, "start": start, "last": start + 1, "cpu": cpu, "cmd": cmd}

    seen = {
        (11, 1): proc(1, t0 - 5, 50.0, "python -u -c import sys;exec(eval(sys.stdin"),
        (12, 1): proc(1, t0 - 5, 40.0, "python -u -c import sys;exec(eval(sys.stdin"),
        (21, 2): proc(11, t0 + 12, 3.0, "python -m vloc.clients.cli serve"),  # b, by 11
        (22, 2): proc(21, t0 + 13, 2.0, "python -c from multiprocessing.spawn"),  # b's too
        (23, 2): proc(12, t0 + 12, 1.5),  # c: worker 12 ran c then
        (24, 2): proc(1, t0 + 1, 4.0),  # not a worker's: counted by kind only
        (25, 2): proc(1, t0 - 100, 0.0, "postgres"),  # idle since before the suite
    }
    by_kind, by_file = attribute(seen, rows, suite_start=t0 - 10)
    assert by_file == {"tests/b.py": 5.0, "tests/c.py": 1.5}
    assert by_kind["vloc serve"] == [1, 3.0]
    assert by_kind["pytest workers"] == [2, 90.0]
    assert "PostgreSQL" not in by_kind
    assert seen[(22, 2)]["file"] == "tests/b.py"
