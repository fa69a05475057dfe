"""docker/: a reproducible image built once, no required variable, a writable /data; and the
CPU quota a container gives the server."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest
import yaml

from tests.conftest import REPO_ROOT
from vloc.app.config import Settings, cpu_quota

DOCKER = REPO_ROOT / "docker"


def test_the_lock_pins_every_runtime_dependency_as_installed():
    import importlib.util

    spec = importlib.util.spec_from_file_location("lock", DOCKER / "lock.py")
    lock = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(lock)
    import tomllib

    roots = tomllib.loads((REPO_ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    expected = {f"{n}=={v}" for n, v in lock.closure(list(roots)).items()}
    pinned = {line for line in (DOCKER / "requirements.lock").read_text().splitlines()
              if line and not line.startswith("#")}
    assert pinned == expected, "run docker/lock.py"
    names = {p.split("==")[0] for p in pinned}
    assert {"fastapi", "opencv-python-headless", "fastapi-offline", "uvloop"} <= names
    assert not names & {"pytest", "ruff", "hypothesis", "schemathesis"}


def test_the_image_installs_the_lock_then_the_service_as_one_package():
    text = (DOCKER / "Dockerfile").read_text()
    assert "pip install -e" not in text and "requirements.lock" in text
    assert "--no-deps -r /tmp/requirements.lock" in text
    # the package installed from the folders tests/test_packaging.py checks, run by its script
    assert "pip install --no-deps /src" in text
    for folder in ("app", "workers", "clients", "migrations"):
        assert f"COPY {folder} /src/{folder}" in text
    assert 'CMD ["vloc", "serve"' in text
    assert (REPO_ROOT / ".dockerignore").read_text().splitlines()[1:] == \
        (DOCKER / "Dockerfile.dockerignore").read_text().splitlines()[1:]


def test_compose_builds_once_and_needs_no_variable():
    compose = yaml.safe_load((DOCKER / "compose.yaml").read_text())
    built = [name for name, svc in compose["services"].items() if "build" in svc]
    assert built == ["api"]
    assert ":?" not in (DOCKER / "compose.yaml").read_text()
    assert compose["services"]["api"]["environment"]["VLOC_ADMIN_KEY"] == "${VLOC_ADMIN_KEY:-}"


def test_an_empty_admin_key_is_unset(monkeypatch, tmp_path):
    monkeypatch.setenv("VLOC_ADMIN_KEY", "")
    assert Settings(data_dir=tmp_path).admin_key is None


@pytest.mark.parametrize(("v2", "v1", "expected"), [
    ("150000 100000\n", None, 1.5), ("max 100000\n", None, None),
    (None, ("200000", "100000"), 2.0), (None, ("-1", "100000"), None), (None, None, None),
])
def test_cpu_quota(tmp_path, v2, v1, expected):
    cpu_max, quota, period = tmp_path / "cpu.max", tmp_path / "quota", tmp_path / "period"
    if v2 is not None:
        cpu_max.write_text(v2)
    if v1 is not None:
        quota.write_text(v1[0])
        period.write_text(v1[1])
    assert cpu_quota(cpu_max, quota, period) == expected


def test_the_worker_count_follows_the_quota(monkeypatch, tmp_path):
    import vloc.app.config as config

    monkeypatch.setattr(config, "cpu_quota", lambda: 1.2)
    monkeypatch.setattr(config.os, "sched_getaffinity", lambda pid: {0, 1, 2, 3})
    assert Settings(data_dir=tmp_path).worker_count == 2
    monkeypatch.setattr(config, "cpu_quota", lambda: None)
    assert Settings(data_dir=tmp_path).worker_count == 4
    assert Settings(data_dir=tmp_path, workers=3).worker_count == 3


def test_the_entrypoint_hands_a_foreign_data_folder_to_the_image_user():
    text = (DOCKER / "entrypoint.sh").read_text()
    assert subprocess.run(["sh", "-n", str(DOCKER / "entrypoint.sh")]).returncode == 0
    assert re.search(r"chown -R vloc:vloc", text) and "exec setpriv" in text
    assert Path(DOCKER / "entrypoint.sh").stat().st_mode & 0o111
