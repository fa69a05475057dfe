"""Fixtures shared by the whole test tree."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]


def shared_dir() -> Path:
    """The shared folder beside the repository, or ``$VLOC_SHARED_DIR`` when set."""
    env = os.environ.get("VLOC_SHARED_DIR")
    return Path(env) if env else REPO_ROOT / ".." / "shared"


@pytest.fixture(scope="session")
def seneca_dir() -> Path:
    """The real UAV data set ``seneca-uav``; the test is skipped where it is absent."""
    path = shared_dir() / "datasets" / "seneca-uav"
    if not (path / "images").is_dir():
        pytest.skip(f"data set seneca-uav not found at {path.resolve()} "
                    "(set VLOC_SHARED_DIR to the folder holding datasets/)")
    return path


# -- service (app/, workers/engine/): real databases and Redis ------------------------------
#
# PostgreSQL and Redis tests skip when the server is unreachable, except under
# VLOC_REQUIRE_SERVICES=1 (CI), where an unreachable server fails them.

POSTGRES_URL = os.environ.get("VLOC_TEST_POSTGRES_URL",
                              "postgresql+psycopg://postgres@127.0.0.1:5432/test")
REDIS_URL = os.environ.get("VLOC_TEST_REDIS_URL", "redis://127.0.0.1:6379/0")


def _service_missing(what: str, exc: Exception) -> None:
    message = f"{what} not reachable ({type(exc).__name__}: {exc})"
    if os.environ.get("VLOC_REQUIRE_SERVICES") == "1":
        pytest.fail(message + " and VLOC_REQUIRE_SERVICES=1")
    pytest.skip(message + "; set VLOC_REQUIRE_SERVICES=1 to make this a failure")


def postgres_schema_url(base_url: str = POSTGRES_URL):
    """A context manager: a fresh schema in the test database, as a URL that uses it."""
    import contextlib
    import uuid

    import psycopg
    from sqlalchemy.engine import make_url

    @contextlib.contextmanager
    def scope():
        url = make_url(base_url)
        plain = url.set(drivername="postgresql").render_as_string(hide_password=False)
        schema = f"vloc_test_{uuid.uuid4().hex[:12]}"
        try:
            conn = psycopg.connect(plain, autocommit=True, connect_timeout=3)
        except psycopg.OperationalError as exc:
            _service_missing(f"PostgreSQL at {url.host}:{url.port}", exc)
        with conn:
            conn.execute(f'CREATE SCHEMA "{schema}"')
            try:
                yield url.update_query_dict({"options": f"-csearch_path={schema}"}) \
                    .render_as_string(hide_password=False)
            finally:
                conn.execute(f'DROP SCHEMA "{schema}" CASCADE')

    return scope()


@pytest.fixture(params=["sqlite", pytest.param("postgres", marks=pytest.mark.postgres)])
def database_url(request, tmp_path) -> Iterator[str]:
    """An empty database: a SQLite file in tmp_path, or a fresh PostgreSQL schema."""
    if request.param == "sqlite":
        yield f"sqlite:///{tmp_path / 'vloc.sqlite3'}"
        return
    with postgres_schema_url() as url:
        yield url


@pytest.fixture
def redis_url() -> str:
    import redis

    client = redis.Redis.from_url(REDIS_URL, socket_connect_timeout=3)
    try:
        client.ping()
    except redis.RedisError as exc:
        _service_missing(f"Redis at {REDIS_URL}", exc)
    finally:
        client.close()
    return REDIS_URL
