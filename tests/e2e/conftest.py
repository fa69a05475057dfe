"""A real ``vloc serve`` process on a free port; the viewer tests' browser, in-process
server and built map."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx
import pytest

from tests.conftest import REPO_ROOT
from tests.e2e.browser import launch_browser, viewer_server, viewer_world
from vloc.clients.demo import free_port


@dataclass
class Server:
    base_url: str
    ws_url: str
    data_dir: Path
    process: subprocess.Popen
    stderr_path: Path

    def admin_key(self) -> str:
        return (self.data_dir / "admin_key").read_text().strip()

    def stop(self, timeout: float = 60.0) -> int:
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            self.process.wait(timeout)
        return self.process.returncode


def start_server(data_dir: Path, *, workers: int = 2, env: dict | None = None,
                 timeout: float = 120.0, args: tuple[str, ...] = (),
                 port: int | None = None) -> Server:
    """``vloc serve`` on ``data_dir``, ready; on ``port`` (a free one by default): a server
    stopped and started again on the same folder and port is, to its clients, restarted."""
    port = port or free_port()
    stderr_path = data_dir.parent / f"server-{port}.log"
    environ = {**os.environ, "VLOC_DATA_DIR": str(data_dir), "VLOC_WORKERS": str(workers),
               "VLOC_LOG_LEVEL": "INFO", **(env or {})}
    environ.pop("VLOC_ADMIN_KEY", None)
    environ.pop("VLOC_DATABASE_URL", None)
    environ.update(env or {})
    process = subprocess.Popen(
        [sys.executable, "-m", "vloc.clients.cli", "serve", "--host", "127.0.0.1", "--port",
         str(port), *args], cwd=REPO_ROOT, env=environ, stdout=subprocess.DEVNULL,
        stderr=stderr_path.open("wb"))
    server = Server(f"http://127.0.0.1:{port}", f"ws://127.0.0.1:{port}", data_dir, process,
                    stderr_path)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if process.poll() is not None:
            pytest.fail(f"the server exited with {process.returncode}:\n"
                        + stderr_path.read_text()[-3000:])
        try:
            if httpx.get(server.base_url + "/readyz", timeout=1.0).status_code == 200:
                return server
        except httpx.TransportError:
            pass
        time.sleep(0.2)
    server.stop()
    pytest.fail("the server did not become ready:\n" + stderr_path.read_text()[-3000:])


def interruptible(cmd, **kwargs) -> subprocess.Popen:
    """Popen of a command that a test stops with Ctrl-C (SIGINT). A test run started as a
    background job of a non-interactive shell (``make test &``, ``nohup``) has SIGINT
    ignored, and a child inherits an ignored signal (but not a handler), so a plain Popen's
    child would never see the test's Ctrl-C: this one starts with Python's own handler."""
    previous = signal.getsignal(signal.SIGINT)
    if previous == signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        return subprocess.Popen(cmd, **kwargs)
    finally:
        signal.signal(signal.SIGINT, previous)


@pytest.fixture
def server(tmp_path) -> Iterator[Server]:
    srv = start_server(tmp_path / "data")
    yield srv
    if srv.process.poll() is None:
        srv.process.kill()
        srv.process.wait(10)


@pytest.fixture(scope="module")
def browser():
    yield from launch_browser()


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    yield from viewer_server(tmp_path_factory.mktemp("viewer"))


@pytest.fixture(scope="module")
def world(live):
    """The built map, its shots and the query frames."""
    return viewer_world(live)
