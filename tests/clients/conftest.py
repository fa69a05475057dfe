"""Fixtures of the client tests: a small geotagged data set, the real app in process, and
the SDK client with a map built on it.

The data set is a seeded random texture seen from above: map images (pass 1) and query
frames (pass 2) are 320x240 crops at known positions, JPEG with EXIF GPS, listed in a
``ground_truth.csv`` -- the layout ``vloc eval`` and ``vloc replay`` read.
"""

from __future__ import annotations

import csv
import math
import sys
import threading
import time
import venv
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
import pytest

from vloc.clients.demo import free_port
from vloc.workers.core.exif import encode_jpeg_with_gps

if TYPE_CHECKING:
    from vloc.clients.sdk import Client

ADMIN_KEY = "client-test-admin-key-0123456789"
LAT0, LON0 = 41.0345, -83.3057
METRES_PER_PIXEL = 0.25
T0 = datetime(2024, 6, 4, 13, 0, 0, tzinfo=UTC)
FAST = {"n_particles": 60}
"""Session parameters that keep a filter step cheap."""


@dataclass(frozen=True)
class Shot:
    name: str
    jpeg: bytes
    lat: float
    lon: float
    captured_at: datetime
    pass_: int


def _texture(seed: int, size: tuple[int, int] = (1400, 900)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    w, h = size
    img = np.full((h, w, 3), 90, np.uint8)
    noise = rng.integers(0, 40, (h // 8, w // 8, 3), dtype=np.uint8)
    img += cv2.resize(noise, (w, h), interpolation=cv2.INTER_CUBIC)
    for _ in range(900):
        colour = tuple(int(c) for c in rng.integers(0, 256, 3))
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        r = int(rng.integers(3, 25))
        if rng.random() < 0.5:
            cv2.circle(img, (x, y), r, colour, -1)
        else:
            cv2.rectangle(img, (x, y), (x + 2 * r, y + int(rng.integers(5, 40))), colour, -1)
    return img


def _shot(texture: np.ndarray, cx: float, cy: float, name: str, t: float, pass_: int) -> Shot:
    w, h = 320, 240
    x0, y0 = int(round(cx - w / 2)), int(round(cy - h / 2))
    crop = np.ascontiguousarray(texture[y0:y0 + h, x0:x0 + w])
    big_h, big_w = texture.shape[:2]
    east, north = (cx - big_w / 2) * METRES_PER_PIXEL, -(cy - big_h / 2) * METRES_PER_PIXEL
    lat = LAT0 + north / 111_320.0
    lon = LON0 + east / (111_320.0 * math.cos(math.radians(LAT0)))
    when = T0 + timedelta(seconds=t)
    jpeg = encode_jpeg_with_gps(crop, quality=90, lat=lat, lon=lon, alt=250.0,
                                captured_at=when)
    return Shot(name, jpeg, lat, lon, when, pass_)


def _lawnmower(n: int, step: float, per_row: int, start=(300.0, 250.0)) -> list[tuple]:
    pts = []
    for i in range(n):
        row, k = divmod(i, per_row)
        col = k if row % 2 == 0 else per_row - 1 - k
        pts.append((start[0] + col * step, start[1] + row * step * 1.5))
    return pts


def make_shots(n_map: int = 10, seed: int = 7) -> tuple[list[Shot], list[Shot]]:
    """Map shots 20 m apart along a lawnmower path, queries half-way between them."""
    texture = _texture(seed)
    pts = _lawnmower(n_map, 80.0, 5)
    maps = [_shot(texture, x, y, f"map_{i:03d}.jpg", 5.0 * i, 1) for i, (x, y) in enumerate(pts)]
    mids = [((a[0] + b[0]) / 2 + 7, (a[1] + b[1]) / 2 - 5) for a, b in zip(pts, pts[1:], strict=False)]
    queries = [_shot(texture, x, y, f"query_{i:03d}.jpg", 600.0 + 5.0 * i, 2)
               for i, (x, y) in enumerate(mids)]
    return maps, queries


def write_dataset(folder: Path, shots: list[Shot]) -> Path:
    """``folder/images/*.jpg`` and ``folder/ground_truth.csv``."""
    (folder / "images").mkdir(parents=True, exist_ok=True)
    with open(folder / "ground_truth.csv", "w", newline="") as fh:
        out = csv.writer(fh)
        out.writerow(["filename", "pass", "captured_at", "lat", "lon", "alt_m"])
        for s in shots:
            (folder / "images" / s.name).write_bytes(s.jpeg)
            out.writerow([s.name, s.pass_, s.captured_at.isoformat(), f"{s.lat:.9f}",
                          f"{s.lon:.9f}", "250.0"])
    return folder


@pytest.fixture(scope="session")
def shots() -> tuple[list[Shot], list[Shot]]:
    return make_shots(10)


@pytest.fixture(scope="session")
def dataset_dir(tmp_path_factory, shots) -> Path:
    maps, queries = shots
    return write_dataset(tmp_path_factory.mktemp("dataset"), maps + queries)


def service_settings(data_dir: Path, **overrides):
    from vloc.app.config import Settings

    values = {"data_dir": data_dir, "workers": 1, "admin_key": ADMIN_KEY,
              "max_upload_bytes": 1_000_000, "max_frame_bytes": 400_000,
              "max_pixels": 2_000_000, "log_json": False, "log_level": "WARNING"}
    return Settings(**(values | overrides))


@pytest.fixture(scope="module")
def app_client(tmp_path_factory) -> Iterator:
    """The app on a fresh SQLite file with one worker process, shared by a test module
    (each test makes its own maps and sessions)."""
    from fastapi.testclient import TestClient

    from vloc.app.main import create_app

    app = create_app(service_settings(tmp_path_factory.mktemp("data")))
    with TestClient(app) as tc:
        yield tc


@pytest.fixture(scope="module")
def vloc(app_client) -> Client:
    """The blocking SDK client on ``app_client``, as the admin, without retries."""
    from vloc.clients.sdk.testing import in_process_client

    return in_process_client(app_client, admin_key=ADMIN_KEY, retry=0)


@pytest.fixture(scope="module")
def built_map(vloc, shots) -> str:
    """The id of a map built from the map shots, one per test module."""
    maps, _ = shots
    m = vloc.create_map("built")
    vloc.upload_images(m.id, [(s.name, s.jpeg) for s in maps])
    vloc.wait_for_job(vloc.build_map(m.id).id, timeout=120)
    return m.id


def bare_environment(env_dir: Path) -> list[str]:
    """Make a virtual environment at ``env_dir`` without a pip of its own (bootstrapping one
    costs seconds) and return the command of this environment's pip acting on it."""
    venv.create(env_dir, with_pip=False)
    return [sys.executable, "-m", "pip", "--python", str(env_dir / "bin" / "python"),
            "--disable-pip-version-check"]


@pytest.fixture(scope="module")
def live_server(tmp_path_factory) -> Iterator[str]:
    """The app served by uvicorn on a free local port (a thread of this process): real
    HTTP and WebSocket connections. Yields the base URL."""
    import uvicorn

    from vloc.app.main import create_app

    app = create_app(service_settings(tmp_path_factory.mktemp("live")))
    port = free_port()
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port,
                                           log_level="warning", lifespan="on"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 120
    while not server.started:
        if not thread.is_alive() or time.monotonic() > deadline:
            pytest.fail("uvicorn did not start")
        time.sleep(0.05)
    yield f"http://127.0.0.1:{port}"
    server.should_exit = True
    thread.join(60)
