"""The ground of the street world: a block of buildings inside a grid of streets.

Seen from above, the route runs round a block on a paved path; beyond a curb lies the
road (8 m of asphalt with a dashed centre line, edge lines, zebra crossings, manholes,
repair patches and cracks), then the sidewalk across the street, then the neighbouring
blocks. The roads continue past the corners as cross streets. Paving slabs get their own
brightness each, asphalt its own grain, so the ground is locally distinctive everywhere.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from clients.world.textures import value_noise

CURB = 1.5          # route -> curb
ROAD = 8.0          # road width
SIDEWALK = 3.0      # sidewalk across the street


@dataclass(frozen=True)
class Block:
    """The block the route goes round (route = rounded rectangle, centre at the origin)."""

    half_x: float
    half_y: float
    radius: float

    def route_distance(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Signed distance to the route (negative inside the block)."""
        r = self.radius
        qx, qy = np.abs(x) - self.half_x + r, np.abs(y) - self.half_y + r
        outside = np.hypot(np.maximum(qx, 0), np.maximum(qy, 0))
        return outside + np.minimum(np.maximum(qx, qy), 0) - r

    def road_offsets(self) -> dict[str, tuple[float, float]]:
        """Each road strip as (low, high) coordinate range across it: north/south strips
        bound y, east/west strips bound x."""
        hx, hy = self.half_x, self.half_y
        return {"n": (hy + CURB, hy + CURB + ROAD), "s": (-hy - CURB - ROAD, -hy - CURB),
                "e": (hx + CURB, hx + CURB + ROAD), "w": (-hx - CURB - ROAD, -hx - CURB)}


def street_ground(rng: np.random.Generator, block: Block, extent: np.ndarray,
                  texel: float) -> np.ndarray:
    """Albedo of the ground over ``extent`` = (xmin, ymin, xmax, ymax).

    Texture columns run east and rows run south (row 0 is the northern edge).

    Returns
    -------
    (H, W, 3) uint8 ndarray, BGR
    """
    xmin, ymin, xmax, ymax = (float(v) for v in extent)
    w, h = int(round((xmax - xmin) / texel)), int(round((ymax - ymin) / texel))
    x = (xmin + (np.arange(w, dtype=np.float32) + 0.5) * texel)[None, :]
    y = (ymax - (np.arange(h, dtype=np.float32) + 0.5) * texel)[:, None]
    grain = rng.standard_normal((h, w), dtype=np.float32)
    blotch = value_noise(rng, (h, w), 1.2 / texel) * 0.6 + value_noise(rng, (h, w), 0.3 / texel) * 0.4
    # Colour planes (B, G, R) keep the big temporaries to one channel at a time.
    img = np.empty((3, h, w), np.float32)
    # Everything that is not paved: grass and bare soil.
    mix = np.clip(0.5 + value_noise(rng, (h, w), 4.0 / texel), 0, 1)
    light = 1.0 + 0.18 * blotch + 0.08 * grain
    for c, (grass, dirt) in enumerate(zip((70, 125, 95), (80, 105, 125), strict=True)):
        img[c] = (grass + (dirt - grass) * mix) * light
    del mix, light

    hx, hy = block.half_x, block.half_y
    in_rect = (np.abs(x) < hx + CURB) & (np.abs(y) < hy + CURB)
    d = block.route_distance(x, y)
    roads = _road_mask(block, x, y)
    walks = _sidewalk_mask(block, x, y) & ~roads
    # Outer blocks: pavement near the street, lawns and yards behind.
    _slabs(img, rng, extent, texel, walks, 0.8, 0.4, (150, 158, 165), grain)
    path = in_rect & (d > -1.4)
    _slabs(img, rng, extent, texel, path, 0.45, 0.3, (135, 150, 170), grain)
    asphalt = np.float32(92) * (1.0 + 0.10 * blotch + 0.09 * grain)
    for c, k in enumerate((1.02, 1.0, 0.98)):
        np.multiply(asphalt, np.float32(k), out=img[c], where=roads)
    del asphalt, blotch, grain
    out = cv2.merge([np.clip(p, 0, 255).astype(np.uint8) for p in img])
    del img
    _curbs(out, block, extent, texel)
    _markings(out, rng, block, extent, texel)
    _road_details(out, rng, block, extent, texel)
    _litter(out, rng, texel)
    return out


def _road_mask(block: Block, x, y) -> np.ndarray:
    roads = np.zeros(np.broadcast_shapes(x.shape, y.shape), bool)
    for name, (lo, hi) in block.road_offsets().items():
        coord = y if name in "ns" else x
        roads |= (coord >= lo) & (coord <= hi)
    return roads


def _sidewalk_mask(block: Block, x, y) -> np.ndarray:
    walks = np.zeros(np.broadcast_shapes(x.shape, y.shape), bool)
    for name, (lo, hi) in block.road_offsets().items():
        coord = y if name in "ns" else x
        if lo > 0:
            walks |= (coord > hi) & (coord <= hi + SIDEWALK)
        else:
            walks |= (coord < lo) & (coord >= lo - SIDEWALK)
    return walks


def _slabs(img, rng, extent, texel, where, size, row_offset, bgr, grain) -> None:
    """Paving slabs in running bond, each with its own brightness, and dark joints.

    Built one row of slabs at a time: a slab row is a strip of texture rows sharing one
    brightness per slab, so the per-texel work is a broadcast, not a per-texel hash.
    """
    h, w = img.shape[1:]
    xmin, ymax = float(extent[0]), float(extent[3])
    x = xmin + (np.arange(w) + 0.5) * texel
    joint = max(1, int(round(0.02 / texel)))
    tone = np.empty((h, w), np.float32)
    r = 0
    while r < h:
        y_centre = ymax - (r + 0.5) * texel
        iy = math.floor(y_centre / size)
        r_end = min(h, r + int((y_centre - iy * size) / texel) + 1)
        shift = (iy % 2) * row_offset * size
        ix = np.floor((x + shift) / size).astype(np.int64)
        ix -= ix.min()
        per_slab = rng.uniform(0.82, 1.12, int(ix.max()) + 1).astype(np.float32)
        line = per_slab[ix]
        line[np.flatnonzero(np.diff(ix)) + 1] *= 0.6        # joints between slabs
        tone[r:r_end] = line
        tone[max(r_end - joint, r):r_end] *= 0.6             # joint below the row
        r = r_end
    tone *= 1.0 + 0.06 * grain
    for c in range(3):
        np.multiply(tone, np.float32(bgr[c]), out=img[c], where=where)


def _to_px(extent, texel, x, y) -> tuple[int, int]:
    return (int(round((x - extent[0]) / texel)), int(round((extent[3] - y) / texel)))


def _curbs(img, block: Block, extent, texel) -> None:
    """Light curb stones along both edges of every road strip."""
    width = max(1, int(round(0.15 / texel)))
    offs = block.road_offsets()
    crossings = []
    for ns in "ns":
        for ew in "ew":
            (y0, y1), (x0, x1) = offs[ns], offs[ew]
            c0, r0 = _to_px(extent, texel, x0 + 0.2, y1 - 0.2)
            c1, r1 = _to_px(extent, texel, x1 - 0.2, y0 + 0.2)
            sl = (slice(max(r0, 0), max(r1, 0)), slice(max(c0, 0), max(c1, 0)))
            crossings.append((sl, img[sl].copy()))
    for name, (lo, hi) in offs.items():
        for edge in (lo, hi):
            if name in "ns":
                r = _to_px(extent, texel, 0, edge)[1]
                img[max(0, r - width // 2):r + width // 2 + 1] = (175, 180, 182)
            else:
                c = _to_px(extent, texel, edge, 0)[0]
                img[:, max(0, c - width // 2):c + width // 2 + 1] = (175, 180, 182)
    # No curbs across the crossings: the roads run on there.
    for sl, patch in crossings:
        img[sl] = patch


def _markings(img, rng, block: Block, extent, texel) -> None:
    """Dashed centre lines, edge lines, zebra crossings at the corners, arrows."""
    white = (225, 228, 230)
    lw = max(1, int(round(0.12 / texel)))
    dash, gap = rng.uniform(2.5, 3.5), rng.uniform(3.0, 5.0)
    phase = rng.uniform(0, dash + gap)
    far = 4 * max(extent[2] - extent[0], extent[3] - extent[1])
    offs = block.road_offsets()
    for name, (lo, hi) in offs.items():
        mid = (lo + hi) / 2
        t = -far + phase
        while t < far:
            a, b = (t, mid), (t + dash, mid)
            if name in "ew":
                a, b = (mid, t), (mid, t + dash)
            cv2.line(img, _to_px(extent, texel, *a), _to_px(extent, texel, *b), white, lw)
            t += dash + gap
    # Zebra crossings across each road just before every corner.
    hx, hy = block.half_x, block.half_y
    for name, (lo, _hi) in offs.items():
        for sign in (-1, 1):
            along = sign * ((hx if name in "ns" else hy) - rng.uniform(2.0, 4.0))
            for k in range(int(ROAD / 1.0)):
                c = lo + 0.5 + k * 1.0
                if name in "ns":
                    p0 = _to_px(extent, texel, along - 1.5, c)
                    p1 = _to_px(extent, texel, along + 1.5, c + 0.5)
                else:
                    p0 = _to_px(extent, texel, c, along - 1.5)
                    p1 = _to_px(extent, texel, c + 0.5, along + 1.5)
                cv2.rectangle(img, p0, p1, white, -1)
    # Arrows painted on the lanes near the middle of each side.
    for name, (lo, hi) in offs.items():
        for lane, direction in (((lo + (lo + hi) / 2) / 2, 1), (((lo + hi) / 2 + hi) / 2, -1)):
            along = rng.uniform(-0.3, 0.3) * (block.half_x if name in "ns" else block.half_y)
            pts = np.array([[0, 0.3], [2.2, 0.3], [2.2, 0.6], [3.0, 0.0], [2.2, -0.6],
                            [2.2, -0.3], [0, -0.3]]) * [direction, 1]
            if name in "ns":
                world = [(along + px, lane + py) for px, py in pts]
            else:
                world = [(lane + py, along + px) for px, py in pts]
            poly = np.array([_to_px(extent, texel, *p) for p in world], np.int32)
            cv2.fillPoly(img, [poly], white, cv2.LINE_AA)


def _road_details(img, rng, block: Block, extent, texel) -> None:
    """Repair patches, cracks and manhole covers scattered over the roads."""
    offs = block.road_offsets()
    span = max(extent[2] - extent[0], extent[3] - extent[1])
    for name, (lo, hi) in offs.items():
        n = int(span / 6)
        for _ in range(n):
            along, across = rng.uniform(-span / 2, span / 2), rng.uniform(lo + 0.3, hi - 0.3)
            p = (along, across) if name in "ns" else (across, along)
            c = _to_px(extent, texel, *p)
            kind = rng.random()
            if kind < 0.35:
                r = max(2, int(round(0.32 / texel)))
                cv2.circle(img, c, r, (70, 72, 75), -1, cv2.LINE_AA)
                cv2.circle(img, c, r, (50, 50, 50), max(1, r // 8), cv2.LINE_AA)
                for k in range(-r + r // 3, r, max(2, r // 3)):
                    cv2.line(img, (c[0] - r // 2, c[1] + k), (c[0] + r // 2, c[1] + k), (55, 55, 58), 1)
            elif kind < 0.65:
                size = (rng.uniform(0.5, 2.5, 2) / texel).astype(int)
                tone = float(rng.uniform(60, 120))
                cv2.rectangle(img, c, (c[0] + size[0], c[1] + size[1]), (tone, tone, tone + 2), -1)
            else:
                pts = np.cumsum(rng.normal(0, 0.4 / texel, (int(rng.integers(4, 10)), 2)), axis=0) + c
                cv2.polylines(img, [pts.astype(np.int32)], False, (45, 45, 48), max(1, int(0.03 / texel)), cv2.LINE_AA)


def _litter(img, rng, texel) -> None:
    """Leaves, chewing gum and stains: small random spots over everything."""
    h, w = img.shape[:2]
    n = int(h * w * texel * texel * 0.6)
    xs, ys = rng.integers(0, w, n), rng.integers(0, h, n)
    radii = np.maximum(1, (rng.uniform(0.01, 0.06, n) / texel)).astype(int)
    tones = rng.uniform(0.55, 1.25, n)
    for x, y, r, t in zip(xs, ys, radii, tones, strict=True):
        c = img[y, x].astype(np.float32) * t
        cv2.circle(img, (int(x), int(y)), int(r), tuple(float(v) for v in np.clip(c, 0, 255)), -1)
