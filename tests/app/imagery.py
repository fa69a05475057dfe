"""Small geotagged aerial-style images for the service tests.

A seeded random texture stands for the ground; map images and query frames are 320x240
crops of it at known positions, encoded as JPEG with the position in EXIF GPS. Ground
sampling is 0.25 m per pixel, so crops 80 px apart are 20 m apart.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta

import cv2
import numpy as np

from vloc.workers.core.exif import encode_jpeg_with_gps

LAT0, LON0, ALT0 = 41.0345, -83.3057, 280.0
METRES_PER_PIXEL = 0.25
CROP = (320, 240)
T0 = datetime(2024, 6, 4, 13, 37, 0, tzinfo=UTC)


@dataclass(frozen=True)
class Shot:
    name: str
    jpeg: bytes
    lat: float
    lon: float
    east: float
    north: float
    captured_at: datetime


def world(seed: int = 7, size: tuple[int, int] = (1400, 900)) -> np.ndarray:
    """A (H, W, 3) uint8 BGR texture of random blobs, lines and rectangles."""
    rng = np.random.default_rng(seed)
    w, h = size
    img = np.full((h, w, 3), 90, np.uint8)
    noise = rng.integers(0, 40, (h // 8, w // 8, 3), dtype=np.uint8)
    img += cv2.resize(noise, (w, h), interpolation=cv2.INTER_CUBIC)
    for _ in range(900):
        colour = tuple(int(c) for c in rng.integers(0, 256, 3))
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        kind = rng.integers(0, 3)
        if kind == 0:
            cv2.circle(img, (x, y), int(rng.integers(3, 25)), colour, -1)
        elif kind == 1:
            cv2.rectangle(img, (x, y), (x + int(rng.integers(5, 40)),
                                        y + int(rng.integers(5, 40))), colour, -1)
        else:
            cv2.line(img, (x, y), (x + int(rng.integers(-60, 60)),
                                   y + int(rng.integers(-60, 60))), colour, 2)
    return img


def to_lat_lon(east: float, north: float) -> tuple[float, float]:
    lat = LAT0 + north / 111_320.0
    lon = LON0 + east / (111_320.0 * math.cos(math.radians(LAT0)))
    return lat, lon


def shot(texture: np.ndarray, cx: float, cy: float, name: str, t: int) -> Shot:
    """The crop centred on pixel (cx, cy), geotagged."""
    w, h = CROP
    x0, y0 = int(round(cx - w / 2)), int(round(cy - h / 2))
    crop = np.ascontiguousarray(texture[y0:y0 + h, x0:x0 + w])
    H, W = texture.shape[:2]
    east, north = (cx - W / 2) * METRES_PER_PIXEL, -(cy - H / 2) * METRES_PER_PIXEL
    lat, lon = to_lat_lon(east, north)
    when = T0 + timedelta(seconds=5 * t)
    jpeg = encode_jpeg_with_gps(crop, quality=88, lat=lat, lon=lon, alt=ALT0,
                                captured_at=when)
    return Shot(name, jpeg, lat, lon, east, north, when)


def path(n: int, *, start: tuple[float, float] = (300, 250), step: float = 80.0,
         per_row: int = 5) -> list[tuple[float, float]]:
    """A lawnmower path of ``n`` points, ``per_row`` per leg."""
    pts = []
    for i in range(n):
        row, k = divmod(i, per_row)
        col = k if row % 2 == 0 else per_row - 1 - k
        pts.append((start[0] + col * step, start[1] + row * step * 1.5))
    return pts


def map_and_queries(n_map: int = 10, *, seed: int = 7) -> tuple[list[Shot], list[Shot]]:
    """Map shots along a path, and query shots half-way between consecutive map shots."""
    texture = world(seed)
    pts = path(n_map)
    maps = [shot(texture, x, y, f"map_{i:03d}.jpg", i) for i, (x, y) in enumerate(pts)]
    mids = [((a[0] + b[0]) / 2 + 7, (a[1] + b[1]) / 2 - 5) for a, b in zip(pts[:-1], pts[1:], strict=True)]
    queries = [shot(texture, x, y, f"query_{i:03d}.jpg", 100 + i)
               for i, (x, y) in enumerate(mids)]
    return maps, queries


def plain_jpeg(level: int = 128, size: tuple[int, int] = (64, 48)) -> bytes:
    """A JPEG without EXIF."""
    img = np.full((size[1], size[0], 3), level, np.uint8)
    cv2.putText(img, "x", (10, 30), cv2.FONT_HERSHEY_SIMPLEX, 1, (255, 255, 255), 2)
    ok, buf = cv2.imencode(".jpg", img)
    assert ok
    return buf.tobytes()


def png(level: int = 128, size: tuple[int, int] = (64, 48)) -> bytes:
    ok, buf = cv2.imencode(".png", np.full((size[1], size[0], 3), level, np.uint8))
    assert ok
    return buf.tobytes()


def png_bomb(width: int = 20_000, height: int = 20_000) -> bytes:
    """A tiny PNG whose header declares a huge image (a decompression bomb)."""
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        body = kind + data
        return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    # One compressed stream of zero rows: kilobytes that inflate to 400 megapixels.
    raw = zlib.compress(b"\x00" * (width + 1) * 16, 9)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", raw)
            + chunk(b"IEND", b""))
