"""Fixtures of the API tests: the real app (with its worker pool) on a real database."""

from __future__ import annotations

import concurrent.futures
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import func, select

from tests.app.imagery import Shot, map_and_queries
from tests.conftest import postgres_schema_url
from vloc.app.config import Settings
from vloc.app.main import create_app
from vloc.app.maps.models import Map
from vloc.app.models import Base
from vloc.app.sessions.models import LocalisationSession

ADMIN_KEY = "test-admin-key-0123456789abcdef"
ADMIN = {"Authorization": f"Bearer {ADMIN_KEY}"}
PROBLEM = "application/problem+json"
UNKNOWN_ID = "5b0f2d4e-1c3a-4e8b-9d7f-2a6c8e0b4f13"
"""A well-formed id that names nothing (fixed, so that every test process collects the same
test ids)."""
FAST = {"n_particles": 60}
"""Session parameters that keep a filter step cheap in tests."""


def service_settings(data_dir: Path, database_url: str, **overrides) -> Settings:
    values = {"data_dir": data_dir, "database_url": database_url, "workers": 1,
              "admin_key": ADMIN_KEY, "max_upload_bytes": 1_000_000,
              "max_frame_bytes": 400_000, "max_pixels": 2_000_000, "log_json": False}
    return Settings(**(values | overrides))


@pytest.fixture(scope="session")
def shots() -> tuple[list[Shot], list[Shot]]:
    """Ten geotagged map images and nine query frames between them."""
    return map_and_queries(10)


@pytest.fixture
def client(tmp_path, database_url) -> Iterator[TestClient]:
    """The app on an empty database, with one worker process."""
    app = create_app(service_settings(tmp_path / "data", database_url))
    with TestClient(app) as c:
        yield c


def jpeg_files(shots: list[Shot]) -> list[tuple]:
    return [("files", (s.name, s.jpeg, "image/jpeg")) for s in shots]


def wait_job(client: TestClient, job_id: str, timeout: float = 120.0) -> dict:
    """Poll a build job until it finishes."""
    deadline = time.monotonic() + timeout
    while True:
        job = client.get(f"/v1/jobs/{job_id}", headers=ADMIN).json()
        if job["status"] in ("done", "failed") or time.monotonic() > deadline:
            return job
        time.sleep(0.05)


def build_map(client: TestClient, shots: list[Shot], name: str = "test map") -> str:
    map_id = client.post("/v1/maps", json={"name": name}, headers=ADMIN).json()["id"]
    r = client.post(f"/v1/maps/{map_id}/images", files=jpeg_files(shots), headers=ADMIN)
    assert r.status_code == 201, r.text
    job = wait_job(client, client.post(f"/v1/maps/{map_id}/build", headers=ADMIN)
                   .json()["job_id"])
    assert job["status"] == "done", job
    return map_id


def snapshot(client: TestClient) -> dict:
    """Everything a rejected request must leave as it was: row counts of every table,
    each map's revision and status, each session's counters, and the files on disk."""
    ctx = client.app.state.ctx
    with ctx.db_sessions() as db:
        counts = {t.name: db.scalar(select(func.count()).select_from(t))
                  for t in Base.metadata.sorted_tables}
        maps = {str(m.id): (m.revision, m.status) for m in db.scalars(select(Map))}
        sessions = {str(s.id): (s.last_seq, s.frames_processed, s.frames_failed, s.state)
                    for s in db.scalars(select(LocalisationSession))}
    files = sorted(str(p.relative_to(ctx.settings.data_dir))
                   for p in ctx.settings.data_dir.rglob("*") if p.is_file()
                   and not p.name.startswith("vloc.sqlite3"))
    return {"counts": counts, "maps": maps, "sessions": sessions, "files": files}


@dataclass
class Service:
    client: TestClient
    map_id: str

    def new_session(self, **body) -> tuple[str, dict]:
        """A session on the built map: its id and its bearer headers."""
        payload = {"map_id": self.map_id, "mode": "hybrid", "params": dict(FAST), "seed": 1}
        r = self.client.post("/v1/sessions", json=payload | body, headers=ADMIN)
        assert r.status_code == 201, r.text
        return r.json()["id"], {"Authorization": f"Bearer {r.json()['token']}"}


@pytest.fixture(scope="module",
                params=["sqlite", pytest.param("postgres", marks=pytest.mark.postgres)])
def module_client(request, tmp_path_factory) -> Iterator[TestClient]:
    """One app per test module and backend (tests isolate themselves by their own maps
    and sessions); one worker process, so a test can hold it."""
    yield from backend_client(request.param, tmp_path_factory)


def backend_client(backend: str, tmp_path_factory, **overrides) -> Iterator[TestClient]:
    """The app on a fresh ``"sqlite"`` file or ``"postgres"`` schema, with settings
    overridden."""
    data = tmp_path_factory.mktemp("service")

    def run(url: str) -> Iterator[TestClient]:
        with TestClient(create_app(service_settings(data / "data", url, **overrides))) as c:
            yield c

    if backend == "sqlite":
        yield from run(f"sqlite:///{data / 'vloc.sqlite3'}")
    else:
        with postgres_schema_url() as url:
            yield from run(url)


@pytest.fixture(scope="module")
def service(module_client, shots) -> Service:
    """The module's app with a map already built (sessions are per test)."""
    return Service(module_client, build_map(module_client, shots[0]))


@pytest.fixture
def hold_worker(module_client, tmp_path) -> Iterator[callable]:
    """``hold()`` occupies the module app's worker until the test ends, so that work
    submitted after it is certainly queued."""
    release = tmp_path / "release"
    held = []

    def hold():
        held.append(module_client.app.state.ctx.engine.call(
            "tests.engine.fakes:wait_for_file", str(release)))

    yield hold
    release.touch()
    # A held worker may have been killed by the test: the futures then hold WorkerDied.
    concurrent.futures.wait(held, 60)
