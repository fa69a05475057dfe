"""pytest plugin of :mod:`test_suite_profile`: one JSON line per test (its id, wall time and
CPU time: this process's and its waited-for children's, over setup, call and teardown) in
``$SUITE_CPU_RECORDS/<worker>.jsonl``."""

from __future__ import annotations

import json
import os
import resource
import time
from pathlib import Path

import pytest


def _cpu_s() -> float:
    own = resource.getrusage(resource.RUSAGE_SELF)
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    folder = os.environ.get("SUITE_CPU_RECORDS")
    cpu, wall = _cpu_s(), time.perf_counter()
    yield
    if folder:
        record = {"id": item.nodeid, "cpu": _cpu_s() - cpu, "wall": time.perf_counter() - wall}
        path = Path(folder) / f"{os.environ.get('PYTEST_XDIST_WORKER', 'main')}.jsonl"
        with path.open("a") as fh:
            fh.write(json.dumps(record) + "\n")
