"""Procedural textures: noise, foliage, bark, car bodies and lettering.

Every texture is drawn from the generator it is given, so each building, car and tree of
a world gets its own texture: places look alike only when they are near each other, which
is what SIFT matching and the global features need to tell places apart. Facades have
their own module, :mod:`clients.world.facades`.

Colours are BGR uint8 (OpenCV order); textures are albedos, lit later per illumination.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

LETTERS = "ABCDEFGHIJKLMNOPRSTUVWXYZ0123456789"
FONTS = (cv2.FONT_HERSHEY_SIMPLEX, cv2.FONT_HERSHEY_DUPLEX, cv2.FONT_HERSHEY_COMPLEX,
         cv2.FONT_HERSHEY_TRIPLEX, cv2.FONT_HERSHEY_PLAIN)


def value_noise(rng: np.random.Generator, shape: tuple[int, int], cell: float) -> np.ndarray:
    """Smooth random field with features about ``cell`` texels wide.

    Returns
    -------
    (h, w) float32 ndarray, values roughly in [-1, 1]
    """
    h, w = shape
    gh, gw = max(2, int(math.ceil(h / cell)) + 1), max(2, int(math.ceil(w / cell)) + 1)
    grid = rng.uniform(-1.0, 1.0, (gh, gw)).astype(np.float32)
    big = cv2.resize(grid, (int((gw - 1) * cell) + 1, int((gh - 1) * cell) + 1),
                     interpolation=cv2.INTER_CUBIC)
    if big.shape[0] < h or big.shape[1] < w:
        big = cv2.resize(grid, (w, h), interpolation=cv2.INTER_CUBIC)
    return big[:h, :w]


def fbm(rng: np.random.Generator, shape: tuple[int, int], cell: float, octaves: int = 4,
        gain: float = 0.5) -> np.ndarray:
    """Fractal (multi-octave) noise, finest octave ``cell / 2**(octaves - 1)`` texels.

    Returns
    -------
    (h, w) float32 ndarray, standard deviation about 0.5
    """
    out = np.zeros(shape, np.float32)
    amp, total = 1.0, 0.0
    for k in range(octaves):
        c = max(cell / 2 ** k, 1.0)
        out += amp * value_noise(rng, shape, c)
        total += amp
        amp *= gain
    return out / total


def jitter_colour(rng: np.random.Generator, bgr, spread: float = 18.0) -> np.ndarray:
    """A colour near ``bgr``: every object of a kind looks a little different."""
    return np.clip(np.asarray(bgr, np.float32) + rng.normal(0.0, spread, 3), 0, 255)


def tinted(rng: np.random.Generator, shape: tuple[int, int], bgr, cell: float,
           amount: float = 0.12, octaves: int = 4) -> np.ndarray:
    """A colour modulated by fractal noise (dirt, weathering, paint)."""
    n = fbm(rng, shape, cell, octaves)
    img = np.asarray(bgr, np.float32)[None, None, :] * (1.0 + amount * n[..., None])
    return np.clip(img, 0, 255).astype(np.uint8)


def random_text(rng: np.random.Generator, n_min: int = 3, n_max: int = 9) -> str:
    n = int(rng.integers(n_min, n_max + 1))
    return "".join(LETTERS[i] for i in rng.integers(0, len(LETTERS), n))


def draw_text(img: np.ndarray, rng: np.random.Generator, box: tuple[int, int, int, int],
              colour, text: str | None = None) -> None:
    """Random lettering fitted into ``box`` = (x0, y0, x1, y1); the signs of shops and
    posters are the most distinctive patches of a street for SIFT."""
    x0, y0, x1, y1 = box
    if x1 - x0 < 6 or y1 - y0 < 4:
        return
    text = text if text is not None else random_text(rng)
    font = FONTS[int(rng.integers(0, len(FONTS)))]
    thick = max(1, int((y1 - y0) / 9))
    (tw, th), _ = cv2.getTextSize(text, font, 1.0, thick)
    scale = min((x1 - x0) * 0.9 / max(tw, 1), (y1 - y0) * 0.7 / max(th, 1))
    if scale <= 0.05:
        return
    (tw, th), _ = cv2.getTextSize(text, font, scale, thick)
    org = (x0 + (x1 - x0 - tw) // 2, y0 + (y1 - y0 + th) // 2)
    cv2.putText(img, text, org, font, scale, tuple(float(c) for c in colour), thick,
                cv2.LINE_AA)


def poster(rng: np.random.Generator, w: int, h: int) -> np.ndarray:
    """An advertising poster: coloured ground, shapes and lettering."""
    bg = rng.integers(20, 250, 3)
    img = np.empty((h, w, 3), np.uint8)
    img[:] = bg
    for _ in range(int(rng.integers(2, 6))):
        c = tuple(int(x) for x in rng.integers(0, 256, 3))
        kind = int(rng.integers(0, 3))
        px, py = int(rng.integers(0, max(w, 1))), int(rng.integers(0, max(h, 1)))
        r = int(rng.integers(max(2, min(w, h) // 8), max(3, min(w, h) // 2)))
        if kind == 0:
            cv2.circle(img, (px, py), r, c, -1, cv2.LINE_AA)
        elif kind == 1:
            cv2.rectangle(img, (px - r, py - r // 2), (px + r, py + r // 2), c, -1)
        else:
            pts = rng.integers(0, [max(w, 1), max(h, 1)], (3, 2)).astype(np.int32)
            cv2.fillConvexPoly(img, pts, c, cv2.LINE_AA)
    fg = tuple(int(255 - x) for x in bg)
    draw_text(img, rng, (0, 0, w, max(h // 3, 1)), fg)
    draw_text(img, rng, (w // 8, h * 2 // 3, w - w // 8, h), fg, random_text(rng, 4, 12))
    return img


def foliage(rng: np.random.Generator, width: int, height: int, bgr,
            half: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Albedo and coverage of one billboard of a crown or bush.

    ``half`` makes a half crown that starts at the trunk (texture column 0) and reaches
    out to the rim; crossed half planes around the trunk sort correctly in depth.

    Returns
    -------
    albedo : (height, width, 3) uint8 ndarray
    alpha : (height, width) uint8 ndarray
    """
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float32)
    cx = 0.0 if half else (width - 1) / 2.0
    rx = (width - 1) if half else width / 2.0
    ry = height / 2.0
    r = np.sqrt(((xs - cx) / max(rx, 1)) ** 2 + ((ys - ry) / max(ry, 1)) ** 2)
    edge = 0.78 + 0.22 * fbm(rng, (height, width), max(width, height) / 4, 3)
    clusters = fbm(rng, (height, width), max(4.0, min(width, height) / 6), 3)
    leaves = value_noise(rng, (height, width), 2.0)
    cover = (r < edge + 0.12 * clusters) & (clusters + 0.35 * leaves > -0.45)
    alpha = np.where(cover, 255, 0).astype(np.uint8)
    base = jitter_colour(rng, bgr, 10.0)
    # Light tops and rims, dark insides and undersides: crowns read as volumes.
    shade = 0.78 + 0.28 * clusters + 0.12 * leaves - 0.18 * (ys / height - 0.5)
    albedo = np.clip(base[None, None, :] * shade[..., None], 0, 255).astype(np.uint8)
    # Transparent texels take the mean leaf colour so that coarse mip levels do not grow
    # dark halos around the crown.
    albedo[~cover] = base.astype(np.uint8)
    return albedo, alpha


def bark(rng: np.random.Generator, width: int, height: int) -> np.ndarray:
    """Bark: grey-brown with vertical furrows."""
    base = jitter_colour(rng, (60, 75, 90), 10.0)
    streaks = cv2.resize(rng.uniform(-1, 1, (max(2, height // 12), width)).astype(np.float32),
                         (width, height), interpolation=cv2.INTER_LINEAR)
    shade = 1.0 + 0.25 * streaks + 0.1 * value_noise(rng, (height, width), 3.0)
    return np.clip(base[None, None, :] * shade[..., None], 0, 255).astype(np.uint8)


CAR_COLOURS = ((235, 235, 235), (190, 190, 185), (40, 40, 40), (30, 30, 170), (140, 60, 20),
               (90, 40, 20), (40, 90, 40), (60, 170, 220), (110, 110, 115), (20, 110, 200))


def car_body_side(rng: np.random.Generator, colour, length: int, height: int,
                  texel: float, wheel_x: tuple[float, float],
                  clearance: float) -> tuple[np.ndarray, np.ndarray]:
    """Side of a car's lower body with wheels; transparent under the sills.

    Parameters
    ----------
    length, height : int
        Texture size in texels; row 0 is the top of the body, the last row the road.
    wheel_x : (2,) float
        Wheel centres as shares of the length.
    clearance : float
        Height of the sills above the road in metres.
    """
    img = tinted(rng, (height, length), colour, 20, 0.05, 2)
    alpha = np.full((height, length), 255, np.uint8)
    sill = height - int(round(clearance / texel))
    alpha[sill:] = 0
    # Shading line along the door middle and a darker lower edge.
    cv2.line(img, (0, height // 3), (length, height // 3),
             tuple(float(c) * 0.8 for c in colour), max(1, height // 30))
    img[sill - max(1, height // 10):sill] = (img[sill - max(1, height // 10):sill] * 0.6)
    wheel_r = int(round(0.31 / texel))
    for share in wheel_x:
        c = (int(share * length), height - wheel_r)
        cv2.circle(img, c, int(wheel_r * 1.15), (25, 25, 25), -1, cv2.LINE_AA)
        cv2.circle(alpha, c, int(wheel_r * 1.15), 255, -1)
        cv2.circle(img, c, wheel_r, (20, 20, 22), -1, cv2.LINE_AA)
        cv2.circle(img, c, int(wheel_r * 0.6), (150, 150, 155), -1, cv2.LINE_AA)
        for k in range(int(rng.integers(4, 7))):
            a = k * 2 * math.pi / 5 + rng.uniform(0, 1)
            tip = (int(c[0] + wheel_r * 0.55 * math.cos(a)), int(c[1] + wheel_r * 0.55 * math.sin(a)))
            cv2.line(img, c, tip, (70, 70, 75), max(1, wheel_r // 8), cv2.LINE_AA)
    # Door handles and seams: a few dark lines.
    for share in rng.uniform(0.35, 0.7, 2):
        x = int(share * length)
        cv2.line(img, (x, 2), (x, sill - 2), tuple(float(c) * 0.55 for c in colour), 1)
    return img, alpha


def car_end(rng: np.random.Generator, colour, width: int, height: int, front: bool,
            clearance: int) -> tuple[np.ndarray, np.ndarray]:
    """Front or back of a car body: lights, grille and a number plate with letters."""
    img = tinted(rng, (height, width), colour, 12, 0.05, 2)
    alpha = np.full((height, width), 255, np.uint8)
    alpha[height - clearance:] = 0
    light = (215, 230, 240) if front else (30, 30, 200)
    lh = max(2, height // 5)
    lw = max(3, width // 5)
    for x0 in (width // 14, width - width // 14 - lw):
        cv2.rectangle(img, (x0, height // 5), (x0 + lw, height // 5 + lh), light, -1)
    if front:
        cv2.rectangle(img, (width // 3, height // 4), (2 * width // 3, height // 2), (30, 30, 30), -1)
    pw, ph = max(6, width * 52 // 180), max(3, height * 11 // 75)
    px, py = (width - pw) // 2, height - clearance - ph - max(1, height // 12)
    cv2.rectangle(img, (px, py), (px + pw, py + ph), (235, 235, 235), -1)
    draw_text(img, rng, (px + 1, py, px + pw - 1, py + ph), (20, 20, 20), random_text(rng, 5, 7))
    return img, alpha


def glass_band(rng: np.random.Generator, colour, width: int, height: int,
               pillars: int) -> np.ndarray:
    """A car cabin side or screen: dark glass between body-coloured pillars."""
    img = np.empty((height, width, 3), np.uint8)
    img[:] = np.asarray(colour, np.uint8)
    glass = np.linspace(110, 35, height, dtype=np.float32)[:, None, None] * np.array(
        [1.0, 0.95, 0.9], np.float32)
    inset = max(1, height // 8)
    img[inset:height - 1, :] = np.clip(glass[inset:height - 1]
                                       + rng.normal(0, 3, (1, width, 1)), 0, 255)
    for k in range(pillars):
        x = int((k + 0.5) * width / max(pillars, 1))
        cv2.line(img, (x, 0), (x, height), tuple(float(c) for c in colour), max(1, width // 40))
    cv2.rectangle(img, (0, 0), (width - 1, height - 1), tuple(float(c) for c in colour),
                  max(1, width // 60))
    return img
