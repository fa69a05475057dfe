"""Workers start with what their engine's caller asked to preload, imported once where they
are forked from; the service asks for every module of its tasks package."""

from __future__ import annotations

import json
import subprocess
import sys

from tests.conftest import REPO_ROOT
from vloc.app.config import Settings
from vloc.app.engine import TASKS, engine_for, task_modules

# A fresh process, so that its forkserver is this engine's (Python keeps one a process).
# ``colorsys`` and ``wave`` are modules nothing here imports otherwise.
OWNER = """
import json, sys
from tests.engine.fakes import loaded
from vloc.workers.engine import LocalEngine

engine = LocalEngine(2, preload=json.loads(sys.argv[1]))
engine.start()
try:
    probe = ["colorsys", "wave", "pycolmap"]
    print(json.dumps([engine.call(loaded, probe).result(60) for _ in range(4)]))
finally:
    engine.close()
"""


def _workers_report(preload: list[str]) -> list[list[bool]]:
    out = subprocess.run([sys.executable, "-c", OWNER, json.dumps(preload)], cwd=REPO_ROOT,
                         capture_output=True, text=True, timeout=120, check=True)
    return json.loads(out.stdout.splitlines()[-1])


def test_workers_start_with_the_modules_asked_for_and_colmap():
    assert _workers_report(["colorsys"]) == [[True, False, True]] * 4
    assert _workers_report([]) == [[False, False, True]] * 4


def test_the_service_preloads_every_module_of_its_tasks_package(tmp_path):
    files = sorted(p.stem for p in (REPO_ROOT / "app" / "tasks").glob("*.py")
                   if p.stem != "__init__")
    assert task_modules() == [f"{TASKS}.{name}" for name in files]
    engine = engine_for(Settings(data_dir=tmp_path, engine="local"))
    assert engine.supervisor.preload[-len(files):] == task_modules()
