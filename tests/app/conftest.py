"""Fixtures of the API tests: the real app (with its worker pool) on a real database."""

from __future__ import annotations

import concurrent.futures
import shutil
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import create_engine, func, insert, select, text

from tests.app.imagery import Shot, map_and_queries
from tests.conftest import postgres_schema_url
from vloc.app.config import Settings
from vloc.app.main import create_app
from vloc.app.maps.models import Map, MapImage
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


@dataclass(frozen=True)
class BuiltMap:
    """A map built through the real app, kept to be copied into other apps."""

    data_dir: Path
    database_url: str
    map_id: str


@pytest.fixture(scope="session")
def built_map(tmp_path_factory, shots) -> BuiltMap:
    """The ten map images built into a map once per test process, by the app on SQLite."""
    data = tmp_path_factory.mktemp("built-map")
    url = f"sqlite:///{data / 'vloc.sqlite3'}"
    with TestClient(create_app(service_settings(data / "data", url))) as c:
        map_id = build_map(c, shots[0])
    return BuiltMap(data / "data", url, map_id)


def install_map(client: TestClient, built: BuiltMap) -> str:
    """Copy a built map into a running app: its rows (the map, its images and their
    features, revisions, vocabularies and build job) into the app's database, whichever it
    is, and its folder (images, packed revisions) into the app's data directory. The app
    then holds the map as if it had built it; its id."""
    ctx = client.app.state.ctx
    source = create_engine(built.database_url)
    try:
        with source.connect() as src, ctx.db_engine.begin() as dst:
            for table in Base.metadata.sorted_tables:
                rows = [dict(r._mapping) for r in src.execute(select(table))]
                if rows:
                    dst.execute(insert(table), rows)
            if dst.dialect.name == "postgresql":  # the copied ids are taken
                dst.execute(text("SELECT setval(pg_get_serial_sequence('map_images', 'id'), "
                                 "(SELECT max(id) FROM map_images))"))
    finally:
        source.dispose()
    shutil.copytree(built.data_dir / "maps" / built.map_id,
                    ctx.settings.data_dir / "maps" / built.map_id)
    return built.map_id


@pytest.fixture(scope="module")
def service(module_client, built_map, shots) -> Service:
    """The module's app with a map already built (sessions are per test): the map every
    such module uses, built once per test process (:func:`built_map`) and copied in, or
    built here where the module's tests have stored images already (their ids would
    clash)."""
    with module_client.app.state.ctx.db_sessions() as db:
        fresh = not db.scalar(select(func.count()).select_from(MapImage))
    return Service(module_client, install_map(module_client, built_map) if fresh
                   else build_map(module_client, shots[0]))


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
