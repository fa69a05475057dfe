"""pytest plugin of :mod:`test_suite_profile`: one JSON line per test (its id, wall time and
CPU time: this process's and its waited-for children's, over setup, call and teardown; its
start and end on the wall clock; the worker's process id) in
``$SUITE_CPU_RECORDS/<worker>.jsonl``."""

from __future__ import annotations

import json
import os
import resource
import time
from pathlib import Path

import pytest


def _cpu_s() -> tuple[float, float]:
    """(this process's CPU, its waited-for children's) so far, in seconds."""
    own = resource.getrusage(resource.RUSAGE_SELF)
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime, children.ru_utime + children.ru_stime


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    folder = os.environ.get("SUITE_CPU_RECORDS")
    cpu, wall, start = _cpu_s(), time.perf_counter(), time.time()
    yield
    if folder:
        own, children = (b - a for a, b in zip(cpu, _cpu_s(), strict=True))
        record = {"id": item.nodeid, "cpu": own + children, "cpu_self": own,
                  "wall": time.perf_counter() - wall,
                  "start": start, "end": time.time(), "pid": os.getpid()}
        path = Path(folder) / f"{os.environ.get('PYTEST_XDIST_WORKER', 'main')}.jsonl"
        with path.open("a") as fh:
            fh.write(json.dumps(record) + "\n")
