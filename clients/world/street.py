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

from vloc.clients.world.textures import value_noise

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
    _paving(img, rng, extent, texel, in_rect & (d > -1.4), x, y, grain)
    asphalt = np.float32(92) * (1.0 + 0.10 * blotch + 0.09 * grain)
    for c, k in enumerate((1.02, 1.0, 0.98)):
        np.multiply(asphalt, np.float32(k), out=img[c], where=roads)
    del asphalt, blotch, grain
    out = cv2.merge([np.clip(p, 0, 255).astype(np.uint8) for p in img])
    del img
    _curbs(out, block, extent, texel)
    _markings(out, rng, block, extent, texel)
    _road_details(out, rng, block, extent, texel)
    _path_details(out, rng, block, extent, texel)
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


PAVINGS = (
    # (slab size m, running-bond offset, BGR colour)
    (0.45, 0.3, (135, 150, 170)),     # beige slabs
    (0.30, 0.5, (118, 120, 126)),     # small grey slabs
    (0.60, 0.0, (150, 155, 160)),     # large square slabs
    (0.20, 0.5, (75, 85, 150)),       # red brick pavers
    (0.12, 0.5, (105, 112, 120)),     # cobbles
    (1.00, 0.0, (160, 165, 165)),     # concrete
)
"""Sidewalk materials; a street changes its paving every few tens of metres."""

PAVING_CELL = 14.0
"""Side of the squares (m) within which the path keeps one paving."""


def _paving(img, rng, extent, texel, path, x, y, grain) -> None:
    """The path round the block, paved in a material that changes from place to place."""
    cx = np.floor(x[0] / PAVING_CELL).astype(np.int64)
    cy = np.floor(y[:, 0] / PAVING_CELL).astype(np.int64)
    table = rng.integers(0, len(PAVINGS), (cy.max() - cy.min() + 1, cx.max() - cx.min() + 1))
    style = table[(cy - cy.min())[:, None], (cx - cx.min())[None, :]]
    for k, (size, offset, bgr) in enumerate(PAVINGS):
        where = path & (style == k)
        if where.any():
            colour = np.clip(np.asarray(bgr) * rng.uniform(0.9, 1.1), 0, 255)
            _slabs(img, rng, extent, texel, where, size, offset, colour, grain)


def _slabs(img, rng, extent, texel, where, size, row_offset, bgr, grain) -> None:
    """Paving slabs in running bond, each with its own brightness, and dark joints.

    Built one row of slabs at a time: a slab row is a strip of texture rows sharing one
    brightness per slab, so the per-texel work is a broadcast, not a per-texel hash.
    Only the rows that hold some of ``where`` are built.
    """
    rows = np.flatnonzero(where.any(axis=1))
    if len(rows) == 0:
        return
    top, bottom = int(rows[0]), int(rows[-1]) + 1
    w = img.shape[2]
    xmin, ymax = float(extent[0]), float(extent[3])
    x = xmin + (np.arange(w) + 0.5) * texel
    joint = max(1, int(round(0.02 / texel)))
    tone = np.empty((bottom - top, w), np.float32)
    r = top
    while r < bottom:
        y_centre = ymax - (r + 0.5) * texel
        iy = math.floor(y_centre / size)
        r_end = min(bottom, r + int((y_centre - iy * size) / texel) + 1)
        shift = (iy % 2) * row_offset * size
        ix = np.floor((x + shift) / size).astype(np.int64)
        ix -= ix.min()
        per_slab = rng.uniform(0.82, 1.12, int(ix.max()) + 1).astype(np.float32)
        line = per_slab[ix]
        line[np.flatnonzero(np.diff(ix)) + 1] *= 0.6        # joints between slabs
        tone[r - top:r_end - top] = line
        tone[max(r_end - joint, r) - top:r_end - top] *= 0.6  # joint below the row
        r = r_end
    tone *= 1.0 + 0.06 * grain[top:bottom]
    for c in range(3):
        np.multiply(tone, np.float32(bgr[c]), out=img[c, top:bottom], where=where[top:bottom])


def _path_details(img, rng, block: Block, extent, texel) -> None:
    """Covers, grates and painted signs on the path, one every few metres."""
    route_len = 4 * (block.half_x + block.half_y)
    for _ in range(int(route_len / 4.0)):
        side = rng.integers(0, 4)
        along = rng.uniform(-1, 1)
        off = rng.uniform(-1.2, 1.2)
        if side < 2:
            p = (along * (block.half_x - block.radius), (1 if side else -1) * (block.half_y + off))
        else:
            p = ((1 if side == 3 else -1) * (block.half_x + off), along * (block.half_y - block.radius))
        c = _to_px(extent, texel, *p)
        kind = rng.random()
        s = max(2, int(round(rng.uniform(0.25, 0.45) / texel)))
        if kind < 0.3:                                   # round manhole cover
            cv2.circle(img, c, s, (80, 84, 88), -1, cv2.LINE_AA)
            for r in range(s // 3, s, max(2, s // 4)):
                cv2.circle(img, c, r, (60, 62, 66), 1, cv2.LINE_AA)
        elif kind < 0.55:                                # square utility cover
            cv2.rectangle(img, (c[0] - s, c[1] - s), (c[0] + s, c[1] + s), (95, 100, 105), -1)
            cv2.rectangle(img, (c[0] - s, c[1] - s), (c[0] + s, c[1] + s), (55, 55, 60), max(1, s // 8))
            cv2.line(img, (c[0] - s, c[1]), (c[0] + s, c[1]), (55, 55, 60), 1)
        elif kind < 0.75:                                # drain grate
            for k in range(-s, s + 1, max(2, s // 4)):
                cv2.line(img, (c[0] + k, c[1] - s // 2), (c[0] + k, c[1] + s // 2), (35, 35, 38), 1)
        else:                                            # painted symbol
            colour = [(255, 255, 255), (0, 200, 255), (60, 60, 220), (200, 120, 40)][int(rng.integers(4))]
            pts = (rng.uniform(-s * 2, s * 2, (int(rng.integers(3, 6)), 2)) + c).astype(np.int32)
            cv2.polylines(img, [pts], True, colour, max(1, s // 5), cv2.LINE_AA)


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
