"""Fixtures shared by the whole test tree."""

from __future__ import annotations

import contextlib
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

# -- parallel runs (pytest-xdist): each worker process has its own databases ---------------
#
# A worker (``PYTEST_XDIST_WORKER`` = gw0, gw1, ...) works in its own PostgreSQL database,
# ``<database>_gw0`` beside the one configured (made on first use), and its own Redis
# database number (1 + its index). Ports are free ones the operating system picks, and data
# folders are under pytest's per-worker temporary directory.

WORKER = os.environ.get("PYTEST_XDIST_WORKER", "")
"""This process's pytest-xdist worker name, or "" in a run without workers."""

RAY_GROUP = "ray"
"""The tests that start or join a Ray cluster: one worker runs all of them, in turn, so that
the machine never runs two clusters at once (:func:`pytest_collection_modifyitems`)."""


def _for_worker_postgres(url: str) -> str:
    from sqlalchemy.engine import make_url

    if not WORKER:
        return url
    parsed = make_url(url)
    return parsed.set(database=f"{parsed.database}_{WORKER}").render_as_string(
        hide_password=False)


def _for_worker_redis(url: str) -> str:
    from urllib.parse import urlsplit, urlunsplit

    if not WORKER:
        return url
    parts = urlsplit(url)
    return urlunsplit(parts._replace(path=f"/{1 + int(WORKER.removeprefix('gw'))}"))


BASE_POSTGRES_URL = os.environ.get("VLOC_TEST_POSTGRES_URL",
                                   "postgresql+psycopg://postgres@127.0.0.1:5432/test")
POSTGRES_URL = _for_worker_postgres(BASE_POSTGRES_URL)
REDIS_URL = _for_worker_redis(os.environ.get("VLOC_TEST_REDIS_URL",
                                             "redis://127.0.0.1:6379/0"))


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config, items) -> None:
    """Groups for pytest-xdist's ``--dist loadgroup`` (``make test``): the tests that share a
    module- or session-wide fixture instance (an app with a built map, a live server, a
    browser) run on one worker, so that it is made once, not once per worker; the tests that
    use Ray run on one worker; every other test goes wherever a worker is free. It runs
    first: xdist's own hook turns the group markers into the node ids it schedules by."""
    for item in items:
        if item.get_closest_marker("xdist_group") is not None:
            continue
        group = _shared_fixture_group(item)
        if group is not None:
            item.add_marker(pytest.mark.xdist_group(group))
    if config.getoption("loadgroup", False):
        _longest_first(items)


def _longest_first(items) -> None:
    """Hand the workers the long groups first (the real-data evaluations, then Ray's), so
    that the short tests fill the gaps instead of one worker finishing a long test alone
    after the others are idle. The order within a group stays as written."""
    def group_of(item):
        mark = item.get_closest_marker("xdist_group")
        return mark.args[0] if mark is not None else item.nodeid

    rank: dict[str, tuple[int, int]] = {}  # group -> (how long, where it first appears)
    for at, item in enumerate(items):
        own = 0 if item.get_closest_marker("slow") else 1 if group_of(item) == RAY_GROUP else 2
        before = rank.get(group_of(item), (own, at))
        rank[group_of(item)] = (min(before[0], own), before[1])
    items.sort(key=lambda item: rank[group_of(item)])


def _shared_fixture_group(item) -> str | None:
    if "ray_cluster" in item.fixturenames:
        return RAY_GROUP
    defs = getattr(item, "_fixtureinfo", None)
    if defs is None:
        return None
    # the module-wide fixtures this test uses, and the parameters they were made with
    shared = []
    for name in item.fixturenames:
        chain = defs.name2fixturedefs.get(name)
        if not chain or chain[-1].scope != "module":
            continue
        params = getattr(item, "callspec", None)
        shared.append(f"{name}={params.params[name]}" if params and name in params.params
                      else name)
    if not shared:
        return None
    # xdist reads the group after the id's last "@", and only when no "]" follows it
    group = item.module.__name__ + "(" + ",".join(sorted(shared)) + ")"
    return group.translate(str.maketrans("[]@", "<>_"))


def _service_missing(what: str, exc: Exception) -> None:
    message = f"{what} not reachable ({type(exc).__name__}: {exc})"
    if os.environ.get("VLOC_REQUIRE_SERVICES") == "1":
        pytest.fail(message + " and VLOC_REQUIRE_SERVICES=1")
    pytest.skip(message + "; set VLOC_REQUIRE_SERVICES=1 to make this a failure")


_worker_database_made = False


def _make_worker_database() -> None:
    """Create this worker's database (:data:`POSTGRES_URL`) beside the configured one, once."""
    global _worker_database_made
    if _worker_database_made or POSTGRES_URL == BASE_POSTGRES_URL:
        return
    import psycopg
    from sqlalchemy.engine import make_url

    base = make_url(BASE_POSTGRES_URL).set(drivername="postgresql")
    name = make_url(POSTGRES_URL).database
    with psycopg.connect(base.render_as_string(hide_password=False), autocommit=True,
                         connect_timeout=3) as conn:
        exists = conn.execute("SELECT 1 FROM pg_database WHERE datname = %s",
                              (name,)).fetchone()
        if not exists:
            # another worker may make it between the two statements
            with contextlib.suppress(psycopg.errors.DuplicateDatabase):
                conn.execute(f'CREATE DATABASE "{name}"')
    _worker_database_made = True


def postgres_schema_url(base_url: str = POSTGRES_URL):
    """A context manager: a fresh schema in the test database, as a URL that uses it."""
    import uuid

    import psycopg
    from sqlalchemy.engine import make_url

    @contextlib.contextmanager
    def scope():
        url = make_url(base_url)
        plain = url.set(drivername="postgresql").render_as_string(hide_password=False)
        schema = f"vloc_test_{uuid.uuid4().hex[:12]}"
        try:
            if base_url == POSTGRES_URL:
                _make_worker_database()
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


def require_redis() -> str:
    """``REDIS_URL`` once Redis answers there; otherwise the test skips (or fails where the
    services are required)."""
    import redis

    client = redis.Redis.from_url(REDIS_URL, socket_connect_timeout=3)
    try:
        client.ping()
    except redis.RedisError as exc:
        _service_missing(f"Redis at {REDIS_URL}", exc)
    finally:
        client.close()
    return REDIS_URL


@pytest.fixture
def redis_url() -> str:
    return require_redis()


# -- Ray: one real local cluster for every test that needs it -------------------------------

@pytest.fixture(scope="session")
def ray_cluster(tmp_path_factory) -> Iterator[str]:
    """The address of a real Ray cluster on this machine (2 CPUs), started once and shared:
    a head started with ``ray start --block``, so that API servers in other processes can
    join it too; this process joins it as a driver. Stopped (its own process group) once the
    last test here that uses it has run (:func:`pytest_runtest_teardown`), or at the end.
    Skipped where Ray is not installed, unless VLOC_REQUIRE_SERVICES=1."""
    import subprocess
    import sys
    import time

    try:
        import ray
    except ImportError as exc:
        _service_missing("Ray (pip install 'vloc[ray]')", exc)
    from vloc.clients.demo import free_port

    port = free_port()
    log = tmp_path_factory.mktemp("ray") / "head.log"
    # A cluster for this machine's tests alone; the servers the tests start inherit this.
    os.environ["RAY_AUTH_MODE"] = "disabled"
    env = dict(os.environ, PYTHONPATH=str(REPO_ROOT), RAY_USAGE_STATS_ENABLED="0")
    head = subprocess.Popen(
        # this interpreter, not the ``ray`` script's: the nodes' workers must import this
        # checkout's code (a script copied with a virtual environment names another one)
        [sys.executable, "-c", "import sys; from ray.scripts.scripts import main; "
         "sys.argv[0] = 'ray'; main()", "start", "--head", "--block",
         f"--port={port}", "--num-cpus=2", "--include-dashboard=false",
         "--node-ip-address=127.0.0.1", "--disable-usage-stats"],
        env=env, stdout=log.open("wb"), stderr=subprocess.STDOUT, start_new_session=True)
    address = f"127.0.0.1:{port}"
    global _ray_head
    _ray_head = (head, port)
    try:
        deadline = time.monotonic() + 90
        while True:
            try:
                ray.init(address=address, include_dashboard=False, log_to_driver=False)
                break
            except (ConnectionError, RuntimeError) as exc:
                if head.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError("the Ray head did not start: "
                                       + log.read_text(errors="replace")[-2000:]) from exc
                time.sleep(0.5)
        yield address
    finally:
        _stop_ray()


_ray_head = None
"""The ``ray start`` process of the cluster this process started and its port, while it
runs."""


def _stop_ray() -> None:
    """Stop the cluster this process started, if it runs (again: nothing)."""
    import signal
    import subprocess

    import ray

    global _ray_head
    if _ray_head is None:
        return
    (head, port), _ray_head = _ray_head, None
    if ray.is_initialized():
        ray.shutdown()
    with contextlib.suppress(ProcessLookupError):
        os.killpg(head.pid, signal.SIGTERM)
    try:
        head.wait(5)
    except subprocess.TimeoutExpired:
        os.killpg(head.pid, signal.SIGKILL)
        head.wait(10)
    # ``ray start`` leaves its address for a later ray.init() without one: not ours now.
    current = Path("/tmp/ray/ray_current_cluster")
    if current.is_file() and current.read_text().strip().endswith(f":{port}"):
        current.unlink()


@pytest.hookimpl(trylast=True)
def pytest_runtest_teardown(item, nextitem) -> None:
    """Stop the Ray cluster after the last test that uses it, not at the end of the session:
    idle, its processes take about 6 % of a core, for the rest of the run. Under ``--dist
    loadgroup`` its tests run in one group, one after another, so this is once the group is
    done; in any run, only once no test after this one uses it (trylast: after the module's
    own fixtures, such as the engines on the cluster, are torn down)."""
    if _ray_head is None or nextitem is None or "ray_cluster" not in item.fixturenames:
        return
    items = item.session.items
    if any("ray_cluster" in later.fixturenames for later in items[items.index(item) + 1:]):
        return
    _stop_ray()
