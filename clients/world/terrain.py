"""The ground of the UAV world: fields, meadows, yards, roads and tracks seen from above.

The land is cut into irregular parcels (a jittered Voronoi partition); each parcel gets a
use and draws its own parameters: crop rows with their own direction, spacing and colour,
meadows with flowers, gravel yards, ponds. Roads and farm tracks cross the parcels. From
5 to 100 m up, as in Flyphone's survey flights (Erhard et al., section 5.1), every place
shows a different mix of these patterns, while overlapping frames share them.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from vloc.clients.world.textures import value_noise

USES = ("field", "field", "field", "meadow", "meadow", "yard", "orchard", "forest", "pond")
CROPS = ((60, 140, 90), (70, 170, 200), (60, 110, 150), (50, 120, 70), (90, 180, 190),
         (40, 80, 120))


@dataclass(frozen=True)
class Parcels:
    """The land-use partition, on a coarse grid of ``cell`` metres.

    Attributes
    ----------
    labels : (gh, gw) int32 ndarray
        Parcel index per coarse cell, row 0 at the northern edge.
    uses : list of str
        Use of each parcel.
    seeds : (P, 2) float64 ndarray
        Parcel centres (east, north).
    cell : float
    """

    labels: np.ndarray
    uses: list[str]
    seeds: np.ndarray
    cell: float

    def use_at(self, extent: np.ndarray, x: float, y: float) -> str:
        r = int((extent[3] - y) / self.cell)
        c = int((x - extent[0]) / self.cell)
        r = min(max(r, 0), self.labels.shape[0] - 1)
        c = min(max(c, 0), self.labels.shape[1] - 1)
        return self.uses[int(self.labels[r, c])]


def parcels(rng: np.random.Generator, extent: np.ndarray, size: float = 35.0,
            cell: float = 0.25) -> Parcels:
    """Irregular parcels about ``size`` metres across."""
    xmin, ymin, xmax, ymax = (float(v) for v in extent)
    n = max(4, int((xmax - xmin) * (ymax - ymin) / size ** 2))
    seeds = np.stack([rng.uniform(xmin, xmax, n), rng.uniform(ymin, ymax, n)], axis=1)
    uses = [USES[int(i)] for i in rng.integers(0, len(USES), n)]
    gw, gh = int(np.ceil((xmax - xmin) / cell)), int(np.ceil((ymax - ymin) / cell))
    gx = xmin + (np.arange(gw) + 0.5) * cell
    gy = ymax - (np.arange(gh) + 0.5) * cell
    # Wobbly borders: distort the coordinates by smooth noise before the nearest seed.
    wob = 4.0 / cell
    px = gx[None, :] + 3.0 * value_noise(rng, (gh, gw), wob)
    py = gy[:, None] + 3.0 * value_noise(rng, (gh, gw), wob)
    best = np.full((gh, gw), np.inf)
    labels = np.zeros((gh, gw), np.int32)
    for i, (sx, sy) in enumerate(seeds):
        d = (px - sx) ** 2 + (py - sy) ** 2
        closer = d < best
        best[closer] = d[closer]
        labels[closer] = i
    return Parcels(labels=labels, uses=uses, seeds=seeds, cell=cell)


def terrain_ground(rng: np.random.Generator, land: Parcels, extent: np.ndarray, texel: float,
                   roads: list[tuple[np.ndarray, np.ndarray, float]]) -> np.ndarray:
    """Albedo of the terrain over ``extent``; columns run east, rows south.

    Parameters
    ----------
    roads : list of (start, end, width)
        Straight roads (asphalt, width >= 4 m) and tracks (gravel, narrower), metres.

    Returns
    -------
    (H, W, 3) uint8 ndarray, BGR
    """
    xmin, ymin, xmax, ymax = (float(v) for v in extent)
    w, h = int(round((xmax - xmin) / texel)), int(round((ymax - ymin) / texel))
    labels = cv2.resize(land.labels.astype(np.float32), (w, h), interpolation=cv2.INTER_NEAREST)
    labels = labels.astype(np.int32)
    x = (xmin + (np.arange(w, dtype=np.float32) + 0.5) * texel)[None, :]
    y = (ymax - (np.arange(h, dtype=np.float32) + 0.5) * texel)[:, None]
    n_parcels = len(land.uses)
    angle = rng.uniform(0, np.pi, n_parcels).astype(np.float32)
    spacing = rng.uniform(0.45, 0.9, n_parcels).astype(np.float32)
    colour = np.array([CROPS[int(i)] for i in rng.integers(0, len(CROPS), n_parcels)], np.float32)
    colour *= rng.uniform(0.85, 1.15, (n_parcels, 1)).astype(np.float32)
    kinds = np.array([USES.index(u) if u in USES else 0 for u in land.uses])
    patches = value_noise(rng, (h, w), 6.0 / texel) * 0.6 + value_noise(rng, (h, w), 1.5 / texel) * 0.4
    grain = rng.standard_normal((h, w), dtype=np.float32)
    # Crop rows: a wave across each parcel's row direction.
    phase = (x * np.cos(angle)[labels] + y * np.sin(angle)[labels]) / spacing[labels]
    rows = np.abs(np.sin(np.pi * phase)).astype(np.float32)
    is_field = kinds[labels] == USES.index("field")
    light = 1.0 + 0.14 * patches + 0.03 * grain
    light = np.where(is_field, light * (0.8 + 0.25 * rows), light)
    base = colour[labels]                                     # (h, w, 3)
    meadow = np.isin(kinds[labels], [USES.index(u) for u in ("meadow", "orchard", "forest")])
    base[meadow] = np.array([70, 135, 90], np.float32) * (1.0 + 0.25 * patches[meadow, None])
    yard = kinds[labels] == USES.index("yard")
    base[yard] = np.array([125, 135, 140], np.float32)
    pond = kinds[labels] == USES.index("pond")
    base[pond] = np.array([70, 70, 40], np.float32) * (1.0 + 0.2 * patches[pond, None])
    img = np.clip(base * light[..., None], 0, 255).astype(np.uint8)
    del base, light, phase, rows, labels
    _flowers(img, rng, meadow, texel)
    _landmarks(img, rng, texel)
    for start, end, width in roads:
        _road(img, rng, extent, texel, start, end, width)
    return img


def _flowers(img, rng, where, texel) -> None:
    """Specks of colour on the meadows."""
    h, w = img.shape[:2]
    n = int(h * w * texel * texel * 3)
    ys, xs = rng.integers(0, h, n), rng.integers(0, w, n)
    keep = where[ys, xs]
    colours = np.array([(240, 240, 240), (40, 200, 230), (200, 80, 200), (60, 60, 220)], np.uint8)
    img[ys[keep], xs[keep]] = colours[rng.integers(0, len(colours), int(keep.sum()))]


def _landmarks(img, rng, texel) -> None:
    """What makes one stretch of field look unlike the next: tyre tracks curving across
    the crops, bare and wet patches, stones and hay bales, dark bushes."""
    h, w = img.shape[:2]
    area = h * w * texel * texel
    for _ in range(int(area / 400)):                    # tyre tracks
        pts = np.cumsum(rng.normal(0, 3.0 / texel, (6, 2)), axis=0) + rng.uniform(0, [w, h])
        gauge = max(1, int(1.6 / texel))
        tone = tuple(float(v) for v in rng.uniform(60, 110, 3))
        for off in (0, gauge):
            cv2.polylines(img, [(pts + off).astype(np.int32)], False, tone,
                          max(1, int(0.35 / texel)), cv2.LINE_AA)
    for _ in range(int(area / 250)):                    # bare or wet patches
        c = rng.uniform(0, [w, h]).astype(int)
        axes = (rng.uniform(0.5, 4.0, 2) / texel).astype(int)
        t = rng.uniform(45, 85) if rng.random() < 0.5 else rng.uniform(100, 150)
        tone = (0.75 * t, 0.95 * t, 1.1 * t)            # wet earth or dry sand, BGR
        cv2.ellipse(img, (int(c[0]), int(c[1])), (int(axes[0]), int(axes[1])),
                    float(rng.uniform(0, 180)), 0, 360, tone, -1, cv2.LINE_AA)
    for _ in range(int(area / 60)):                     # stones, bales, bushes
        c = (int(rng.uniform(0, w)), int(rng.uniform(0, h)))
        r = max(2, int(rng.uniform(0.2, 1.0) / texel))
        kind = rng.random()
        if kind < 0.4:
            cv2.circle(img, c, r, (170, 200, 215), -1, cv2.LINE_AA)
            cv2.circle(img, c, max(1, r // 2), (140, 170, 190), max(1, r // 6), cv2.LINE_AA)
        elif kind < 0.7:
            cv2.circle(img, c, r, tuple(float(v) for v in rng.uniform(120, 190, 3)), -1, cv2.LINE_AA)
        else:
            for _ in range(4):
                o = (rng.normal(0, r / 2, 2)).astype(int)
                cv2.circle(img, (c[0] + int(o[0]), c[1] + int(o[1])), r, (30, 75, 40), -1, cv2.LINE_AA)


def _to_px(extent, texel, p) -> tuple[int, int]:
    return (int(round((p[0] - extent[0]) / texel)), int(round((extent[3] - p[1]) / texel)))


def _road(img, rng, extent, texel, start, end, width) -> None:
    a, b = _to_px(extent, texel, start), _to_px(extent, texel, end)
    thick = max(1, int(round(width / texel)))
    if width >= 4.0:
        cv2.line(img, a, b, (175, 178, 180), thick + max(2, int(0.6 / texel)), cv2.LINE_AA)
        cv2.line(img, a, b, (88, 90, 92), thick, cv2.LINE_AA)
        d = np.asarray(end, float) - np.asarray(start, float)
        length = float(np.linalg.norm(d))
        dash, gap = 3.0, 6.0
        t = rng.uniform(0, dash + gap)
        while t < length:
            p0 = np.asarray(start) + d * (t / length)
            p1 = np.asarray(start) + d * (min(t + dash, length) / length)
            cv2.line(img, _to_px(extent, texel, p0), _to_px(extent, texel, p1), (230, 230, 230),
                     max(1, int(0.15 / texel)))
            t += dash + gap
        for _ in range(int(length / 15)):            # patches and manholes
            p = np.asarray(start) + d * rng.uniform(0, 1) + rng.normal(0, width / 5, 2)
            r = max(1, int(rng.uniform(0.3, 1.2) / texel))
            tone = float(rng.uniform(60, 120))
            cv2.circle(img, _to_px(extent, texel, p), r, (tone, tone, tone), -1)
    else:
        cv2.line(img, a, b, (110, 145, 165), thick, cv2.LINE_AA)
        # Wheel ruts with grass between them.
        d = np.asarray(end, float) - np.asarray(start, float)
        n = np.array([-d[1], d[0]]) / max(np.linalg.norm(d), 1e-9)
        cv2.line(img, _to_px(extent, texel, start), _to_px(extent, texel, end), (75, 130, 95),
                 max(1, int(0.4 / texel)), cv2.LINE_AA)
        for s in (-0.7, 0.7):
            cv2.line(img, _to_px(extent, texel, start + s * n), _to_px(extent, texel, end + s * n),
                     (90, 120, 140), max(1, int(0.25 / texel)), cv2.LINE_AA)
