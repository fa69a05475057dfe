"""Procedural building facades and roofs.

A building draws one style (wall material, floor height, window type and rhythm, ground
floor use) and every facade of it draws its own details from that style: each window has
its own curtains, blinds or reflections, shop fronts carry random lettering, walls carry
posters, pipes and stains. Windows repeat, as they do on real buildings, but no two
windows are identical, so SIFT's ratio test still finds the right one.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from vloc.clients.world.textures import draw_text, fbm, jitter_colour, poster, tinted

WALLS = ((200, 215, 225), (170, 200, 225), (150, 180, 205), (215, 215, 210), (190, 200, 200),
         (120, 140, 170), (160, 170, 175), (110, 120, 150), (205, 225, 235), (140, 150, 160))
BRICKS = ((60, 75, 140), (55, 70, 120), (70, 95, 150), (80, 90, 110))
FRAMES = ((235, 235, 235), (45, 45, 45), (40, 60, 90), (90, 110, 100))
CURTAINS = ((200, 210, 220), (60, 60, 150), (150, 90, 60), (210, 200, 170), (90, 150, 90))


@dataclass(frozen=True)
class FacadeStyle:
    """What all facades of one building share."""

    wall: tuple[float, float, float]
    brick: bool
    floor_h: float
    ground_h: float
    window_w: float
    window_h: float
    spacing: float
    frame: tuple[int, int, int]
    mullions: int
    shops: float
    cornice: bool


def facade_style(rng: np.random.Generator) -> FacadeStyle:
    """Draw a building's style."""
    brick = bool(rng.random() < 0.3)
    wall = BRICKS[int(rng.integers(len(BRICKS)))] if brick else WALLS[int(rng.integers(len(WALLS)))]
    spacing = float(rng.uniform(1.8, 3.4))
    return FacadeStyle(
        wall=tuple(float(c) for c in jitter_colour(rng, wall, 12.0)), brick=brick,
        floor_h=float(rng.uniform(2.8, 3.5)), ground_h=float(rng.uniform(3.2, 4.4)),
        window_w=float(rng.uniform(0.8, min(1.8, 0.7 * spacing))),
        window_h=float(rng.uniform(1.2, 1.9)), spacing=spacing,
        frame=FRAMES[int(rng.integers(len(FRAMES)))], mullions=int(rng.integers(0, 3)),
        shops=float(rng.uniform(0.0, 0.9)), cornice=bool(rng.random() < 0.5))


def facade(rng: np.random.Generator, style: FacadeStyle, width_m: float, height_m: float,
           texel: float) -> np.ndarray:
    """Albedo of one facade; row 0 is the eaves, the last row meets the ground.

    Returns
    -------
    (round(height_m / texel), round(width_m / texel), 3) uint8 ndarray, BGR
    """
    w, h = max(4, int(round(width_m / texel))), max(4, int(round(height_m / texel)))
    img = tinted(rng, (h, w), style.wall, 1.5 / texel, 0.10)
    if style.brick:
        _bricks(img, rng, texel)
    # Stains running down from the eaves and a darker plinth.
    stains = np.clip(fbm(rng, (h, w), 25, 3) * np.linspace(1.0, 0.3, h)[:, None], 0, 1)
    img[:] = np.clip(img * (1.0 - 0.25 * stains[..., None]), 0, 255).astype(np.uint8)
    plinth = int(round(0.35 / texel))
    img[h - plinth:] = (img[h - plinth:] * 0.7).astype(np.uint8)
    ground_rows = min(h, int(round(style.ground_h / texel)))
    _upper_floors(img, rng, style, texel, h - ground_rows)
    _ground_floor(img, rng, style, texel, h - ground_rows, h - plinth // 2)
    for _ in range(int(rng.integers(0, 3))):           # drain pipes
        x = int(rng.integers(0, w))
        cv2.line(img, (x, 0), (x, h), (90, 95, 100), max(1, int(0.08 / texel)))
    return img


def roof(rng: np.random.Generator, width_m: float, depth_m: float, texel: float) -> np.ndarray:
    """Albedo of a flat or tiled roof seen from above (UAV views)."""
    w, h = max(4, int(round(width_m / texel))), max(4, int(round(depth_m / texel)))
    colour = [(60, 70, 150), (70, 70, 75), (110, 110, 105), (50, 60, 90), (130, 140, 140)][
        int(rng.integers(5))]
    img = tinted(rng, (h, w), jitter_colour(rng, colour, 10), 30, 0.15)
    step = max(2, int(round(0.4 / texel)))
    img[::step] = (img[::step] * 0.75).astype(np.uint8)
    for _ in range(int(rng.integers(1, 5))):           # chimneys, skylights, vents
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        s = max(2, int(rng.uniform(0.4, 1.2) / texel))
        cv2.rectangle(img, (x, y), (x + s, y + s), tuple(int(c) for c in rng.integers(20, 200, 3)), -1)
    return img


def _paste(img: np.ndarray, patch: np.ndarray, x: int, y: int) -> None:
    """Copy ``patch`` with its top-left corner at (x, y), clipped to the image."""
    h, w = img.shape[:2]
    x0, y0 = max(x, 0), max(y, 0)
    x1, y1 = min(x + patch.shape[1], w), min(y + patch.shape[0], h)
    if x1 > x0 and y1 > y0:
        img[y0:y1, x0:x1] = patch[y0 - y:y1 - y, x0 - x:x1 - x]


def _bricks(img: np.ndarray, rng: np.random.Generator, texel: float) -> None:
    h, w = img.shape[:2]
    course = max(2, int(round(0.075 / texel)))
    length = max(3, int(round(0.25 / texel)))
    rows = np.arange(h) // course
    offset = (rows % 2) * (length // 2)
    brick_id = ((np.arange(w)[None, :] + offset[:, None]) // length) + 1000 * rows[:, None]
    shade = 0.85 + 0.3 * ((brick_id * 2654435761 % 1000) / 1000.0)   # per-brick hash
    img[:] = np.clip(img * shade[..., None], 0, 255).astype(np.uint8)
    img[::course] = (img[::course] * 0.8 + 40).astype(np.uint8)   # mortar courses


def _window(img: np.ndarray, rng: np.random.Generator, style: FacadeStyle,
            box: tuple[int, int, int, int], texel: float) -> None:
    x0, y0, x1, y1 = box
    if x1 - x0 < 3 or y1 - y0 < 3:
        return
    fw = max(1, int(round(0.07 / texel)))
    cv2.rectangle(img, (x0 - fw, y0 - fw), (x1 + fw, y1 + fw), style.frame, -1)
    # Glass reflects the sky at the top and shows the dark room below.
    top = rng.uniform(90, 170)
    grad = np.linspace(top, rng.uniform(25, 60), y1 - y0, dtype=np.float32)
    tint = np.array([1.0, 0.95, 0.85], np.float32) * rng.uniform(0.9, 1.1, 3)
    img[y0:y1, x0:x1] = np.clip(grad[:, None, None] * tint, 0, 255).astype(np.uint8)
    kind = rng.random()
    if kind < 0.3:                                      # curtains, left and right
        c = jitter_colour(rng, CURTAINS[int(rng.integers(len(CURTAINS)))], 15)
        cw = int((x1 - x0) * rng.uniform(0.15, 0.45))
        img[y0:y1, x0:x0 + cw] = c
        img[y0:y1, x1 - int((x1 - x0) * rng.uniform(0.1, 0.4)):x1] = c * 0.9
    elif kind < 0.5:                                    # blinds part way down
        down = y0 + int((y1 - y0) * rng.uniform(0.2, 0.9))
        img[y0:down, x0:x1] = jitter_colour(rng, (200, 205, 210), 20)
        img[y0:down:max(2, int(0.06 / texel)), x0:x1] = (150, 150, 150)
    elif kind < 0.6:                                    # shutters closed
        c = jitter_colour(rng, (60, 110, 80), 30)
        img[y0:y1, x0:x1] = c
        img[y0:y1:max(2, int(0.08 / texel)), x0:x1] = c * 0.7
    elif kind < 0.7:                                    # a lit room with a lamp
        img[y0:y1, x0:x1] = jitter_colour(rng, (120, 180, 220), 20)
        cx = int(rng.integers(x0, x1))
        cv2.circle(img, (cx, y0 + (y1 - y0) // 4), max(1, (x1 - x0) // 6), (230, 245, 255), -1)
    if rng.random() < 0.15:                             # a plant on the sill
        cv2.circle(img, (int(rng.integers(x0, x1)), y1), max(2, (x1 - x0) // 5),
                   tuple(float(c) for c in jitter_colour(rng, (40, 120, 50), 20)), -1)
    for k in range(1, style.mullions + 1):
        x = x0 + k * (x1 - x0) // (style.mullions + 1)
        cv2.line(img, (x, y0), (x, y1), style.frame, max(1, fw // 2))
    if style.mullions:
        y = y0 + (y1 - y0) // 3
        cv2.line(img, (x0, y), (x1, y), style.frame, max(1, fw // 2))
    sill = max(1, int(round(0.05 / texel)))
    cv2.rectangle(img, (x0 - 2 * fw, y1 + fw), (x1 + 2 * fw, y1 + fw + sill), (200, 200, 200), -1)


def _upper_floors(img, rng, style: FacadeStyle, texel: float, bottom: int) -> None:
    h, w = img.shape[:2]
    floor = max(4, int(round(style.floor_h / texel)))
    spacing = max(4, int(round(style.spacing / texel)))
    ww, wh = int(round(style.window_w / texel)), int(round(style.window_h / texel))
    n_cols = max(1, (w - spacing // 2) // spacing)
    margin = (w - n_cols * spacing) // 2
    y_floor = bottom
    while y_floor - floor >= int(0.6 / texel):
        top = y_floor - floor
        sill_y = y_floor - int(round(0.9 / texel))
        for c in range(n_cols):
            if rng.random() < 0.04:                     # a bricked-up window
                continue
            cx = margin + c * spacing + spacing // 2
            _window(img, rng, style, (cx - ww // 2, sill_y - wh, cx + ww // 2, sill_y), texel)
        if rng.random() < 0.25:                          # a balcony in front of one window
            cx = margin + int(rng.integers(0, n_cols)) * spacing + spacing // 2
            bw = int(ww * 1.8)
            y = sill_y + int(0.1 / texel)
            cv2.rectangle(img, (cx - bw // 2, y - int(1.0 / texel)), (cx + bw // 2, y), (70, 70, 70), max(1, int(0.04 / texel)))
            for x in range(cx - bw // 2, cx + bw // 2, max(2, int(0.12 / texel))):
                cv2.line(img, (x, y - int(1.0 / texel)), (x, y), (60, 60, 60), 1)
        if style.cornice:
            cv2.rectangle(img, (0, top), (w, top + max(1, int(0.15 / texel))),
                          tuple(float(c) * 0.85 for c in style.wall), -1)
        y_floor = top


def _ground_floor(img, rng, style: FacadeStyle, texel: float, top: int, bottom: int) -> None:
    h, w = img.shape[:2]
    x = int(rng.integers(0, max(1, int(1.5 / texel))))
    while x < w - int(1.0 / texel):
        unit = int(rng.uniform(2.5, 7.0) / texel)
        x1 = min(w, x + unit)
        r = rng.random()
        if r < style.shops:
            _shop(img, rng, (x, top, x1, bottom), texel)
        elif r < style.shops + 0.25:
            _door(img, rng, (x, top, x1, bottom), texel, style)
        elif r < style.shops + 0.4:
            _garage(img, rng, (x, top, x1, bottom), texel)
        else:
            _wall_items(img, rng, (x, top, x1, bottom), texel, style)
        x = x1 + int(rng.uniform(0.3, 1.5) / texel)


def _shop(img, rng, box, texel) -> None:
    x0, y0, x1, y1 = box
    sign_h = max(3, int(rng.uniform(0.5, 0.9) / texel))
    y_sign = y0 + int(0.3 / texel)
    bg = tuple(int(c) for c in rng.integers(10, 250, 3))
    cv2.rectangle(img, (x0, y_sign), (x1, y_sign + sign_h), bg, -1)
    draw_text(img, rng, (x0, y_sign, x1, y_sign + sign_h), tuple(255 - c for c in bg))
    gy0 = y_sign + sign_h + int(0.2 / texel)
    grad = np.linspace(rng.uniform(80, 140), rng.uniform(20, 50), max(1, y1 - gy0))
    img[gy0:y1, x0:x1] = np.clip(grad[:, None, None] * rng.uniform(0.85, 1.1, 3), 0, 255)
    # Goods behind the glass: a few coloured blocks and a poster.
    for _ in range(int(rng.integers(2, 6))):
        gx, gw = int(rng.integers(x0, max(x0 + 1, x1 - 4))), int(rng.uniform(0.2, 0.8) / texel)
        gh = int(rng.uniform(0.2, 1.0) / texel)
        cv2.rectangle(img, (gx, y1 - gh), (gx + gw, y1), tuple(int(c) for c in rng.integers(30, 240, 3)), -1)
    if rng.random() < 0.6 and x1 - x0 > int(1.0 / texel):
        pw, ph = int(0.6 / texel), int(0.85 / texel)
        px = int(rng.integers(x0, x1 - pw))
        _paste(img, poster(rng, pw, ph), px, gy0 + 2)
    for k in range(1, int(rng.integers(1, 4))):
        x = x0 + k * (x1 - x0) // 3
        cv2.line(img, (x, gy0), (x, y1), (50, 50, 50), max(1, int(0.05 / texel)))


def _door(img, rng, box, texel, style: FacadeStyle) -> None:
    x0, y0, x1, y1 = box
    dw, dh = int(rng.uniform(1.0, 1.8) / texel), int(rng.uniform(2.1, 2.6) / texel)
    dx = int(rng.integers(x0, max(x0 + 1, x1 - dw)))
    colour = tuple(float(c) for c in jitter_colour(rng, [(40, 60, 100), (30, 30, 30), (120, 60, 30), (180, 180, 180)][int(rng.integers(4))], 15))
    cv2.rectangle(img, (dx, y1 - dh), (dx + dw, y1), colour, -1)
    cv2.rectangle(img, (dx, y1 - dh), (dx + dw, y1), style.frame, max(1, int(0.06 / texel)))
    cv2.rectangle(img, (dx + dw // 5, y1 - dh + dh // 8), (dx + dw - dw // 5, y1 - dh // 2),
                  (70, 60, 50), -1)
    plate = int(0.25 / texel)
    cv2.rectangle(img, (dx + dw + 3, y1 - dh // 2), (dx + dw + 3 + plate, y1 - dh // 2 + plate), (220, 120, 40), -1)
    draw_text(img, rng, (dx + dw + 3, y1 - dh // 2, dx + dw + 3 + plate, y1 - dh // 2 + plate), (255, 255, 255), str(int(rng.integers(1, 120))))
    _window(img, rng, style, (x0 + (x1 - x0) * 3 // 4 - int(0.5 / texel), y1 - int(2.4 / texel), x0 + (x1 - x0) * 3 // 4 + int(0.5 / texel), y1 - int(0.9 / texel)), texel)


def _garage(img, rng, box, texel) -> None:
    x0, y0, x1, y1 = box
    gw = min(x1 - x0, int(rng.uniform(2.4, 3.2) / texel))
    gh = int(rng.uniform(2.0, 2.4) / texel)
    c = jitter_colour(rng, (150, 150, 150), 40)
    img[y1 - gh:y1, x0:x0 + gw] = c
    step = max(2, int(0.15 / texel))
    img[y1 - gh:y1:step, x0:x0 + gw] = c * 0.6
    if rng.random() < 0.5:
        for _ in range(int(rng.integers(2, 6))):        # graffiti strokes
            pts = np.stack([rng.integers(x0, x0 + gw, 4), rng.integers(y1 - gh, y1, 4)], 1)
            cv2.polylines(img, [pts.astype(np.int32)], False, tuple(int(v) for v in rng.integers(0, 256, 3)), max(1, int(0.08 / texel)), cv2.LINE_AA)


def _wall_items(img, rng, box, texel, style: FacadeStyle) -> None:
    x0, y0, x1, y1 = box
    if rng.random() < 0.6:
        pw, ph = int(rng.uniform(0.6, 1.4) / texel), int(rng.uniform(0.8, 1.9) / texel)
        if pw < x1 - x0:
            px = int(rng.integers(x0, x1 - pw))
            py = y1 - ph - int(rng.uniform(0.5, 1.0) / texel)
            if py > y0:
                _paste(img, poster(rng, pw, ph), px, py)
    if rng.random() < 0.7:
        _window(img, rng, style, (x0 + (x1 - x0) // 2 - int(0.6 / texel), y0 + int(0.9 / texel), x0 + (x1 - x0) // 2 + int(0.6 / texel), y0 + int(2.3 / texel)), texel)
