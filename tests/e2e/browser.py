"""A headless Chromium for the viewer's tests, and the app under a real uvicorn server in this
process (so a test can also publish on its streams).

The browser is Debian's ``chromium`` (or ``VLOC_CHROMIUM``) driven by Playwright; no browser is
ever downloaded. Without one the tests skip, except where ``VLOC_REQUIRE_SERVICES=1`` (CI),
where they fail.
"""

from __future__ import annotations

import os
import shutil
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field

import pytest

from vloc.clients.demo import free_port

CANDIDATES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")


def chromium_path() -> str | None:
    """The Chromium executable to drive: ``VLOC_CHROMIUM`` or the first found on PATH."""
    explicit = os.environ.get("VLOC_CHROMIUM")
    if explicit:
        return explicit if os.access(explicit, os.X_OK) else None
    for name in CANDIDATES:
        if (found := shutil.which(name)) is not None:
            return found
    return None


def unavailable(reason: str) -> None:
    if os.environ.get("VLOC_REQUIRE_SERVICES") == "1":
        pytest.fail(f"{reason} (required: VLOC_REQUIRE_SERVICES=1)")
    pytest.skip(reason)


def launch_browser(args: tuple[str, ...] = ()) -> Iterator[object]:
    """Yield a Playwright ``Browser`` on the system's Chromium (``args``: its flags)."""
    try:
        from playwright.sync_api import Error, sync_playwright
    except ImportError:
        unavailable("Playwright is not installed (pip install -e '.[dev]')")
    path = chromium_path()
    if path is None:
        unavailable("no Chromium found (apt-get install chromium, or set VLOC_CHROMIUM)")
    with sync_playwright() as pw:
        try:
            browser = pw.chromium.launch(executable_path=path, headless=True, args=list(args))
        except Error as exc:
            unavailable(f"Chromium at {path} does not start: {exc}")
        try:
            yield browser
        finally:
            browser.close()


@dataclass
class PageLog:
    """What a page did wrong: console errors, failed requests, HTTP errors; and every URL
    it asked for."""

    errors: list[str] = field(default_factory=list)
    urls: list[str] = field(default_factory=list)

    def watch(self, page) -> None:
        page.on("console", lambda m: m.type == "error" and self.errors.append(
            f"console: {m.text}"))
        page.on("pageerror", lambda e: self.errors.append(f"page error: {e}"))
        page.on("requestfailed", lambda r: self.errors.append(
            f"request failed: {r.url} {r.failure}"))
        page.on("request", lambda r: self.urls.append(r.url))
        page.on("response", lambda r: r.status >= 400 and self.errors.append(
            f"HTTP {r.status}: {r.url}"))
        page.on("websocket", lambda ws: self.urls.append(ws.url))


@dataclass
class LiveServer:
    base_url: str
    app: object
    server: object
    thread: threading.Thread

    @property
    def loop(self):
        return self.app.state.ctx.intake.loop

    def publish(self, session_id: str, message: dict) -> None:
        """Put a message on a session's stream, as the intake does for an estimate."""
        hub = self.app.state.ctx.hub
        self.loop.call_soon_threadsafe(hub.publish, session_id, message)


def serve_in_thread(settings, timeout: float = 60.0) -> Iterator[LiveServer]:
    """``create_app(settings)`` under uvicorn on a free port, until the generator closes."""
    import uvicorn

    from vloc.app.main import create_app

    app = create_app(settings)
    port = free_port()
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port,
                                           log_level="warning", lifespan="on"))
    thread = threading.Thread(target=server.run, name="viewer-test-server", daemon=True)
    thread.start()
    deadline = time.monotonic() + timeout
    while not server.started:
        if not thread.is_alive() or time.monotonic() > deadline:
            pytest.fail("the server did not start")
        time.sleep(0.05)
    try:
        yield LiveServer(f"http://127.0.0.1:{port}", app, server, thread)
    finally:
        server.should_exit = True
        thread.join(60)


# -- the viewer tests' server and map (fixtures in conftest.py) ------------------------------

N_MAP = 10
TILE_URL = "https://tiles.invalid/{z}/{x}/{y}.png"
"""Never reached: the tests answer its requests inside the browser."""


def viewer_server(data) -> Iterator[LiveServer]:
    from tests.app.conftest import service_settings

    settings = service_settings(data / "data", f"sqlite:///{data / 'vloc.sqlite3'}",
                                viewer_tile_url=TILE_URL, viewer_tile_attribution="test tiles")
    yield from serve_in_thread(settings)


def viewer_world(live: LiveServer) -> dict:
    """A map of N_MAP geotagged images built over HTTP: its id, its shots, query frames."""
    import httpx

    from tests.app.conftest import ADMIN
    from tests.app.imagery import map_and_queries

    maps, queries = map_and_queries(N_MAP)
    with httpx.Client(base_url=live.base_url, headers=ADMIN, timeout=60) as http:
        map_id = http.post("/v1/maps", json={"name": "viewer test"}).json()["id"]
        files = [("files", (s.name, s.jpeg, "image/jpeg")) for s in maps]
        r = http.post(f"/v1/maps/{map_id}/images", files=files)
        assert r.status_code == 201 and len(r.json()["accepted"]) == N_MAP, r.text
        job_id = http.post(f"/v1/maps/{map_id}/build").json()["job_id"]
        deadline = time.monotonic() + 120
        while (job := http.get(f"/v1/jobs/{job_id}").json())["status"] not in ("done",
                                                                               "failed"):
            assert time.monotonic() < deadline, job
            time.sleep(0.1)
        assert job["status"] == "done", job
    return {"map_id": map_id, "maps": maps, "queries": queries}
