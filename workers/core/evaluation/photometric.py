"""Photometric variants of query images, to emulate a change of illumination.

Weiss et al. (2008, section V) and Erhard et al. (Flyphone, section 5, datasets C and S)
evaluate localisation with map and query images taken under different light: sun against
cloud, afternoon against dusk, with and without hard cast shadows. These variants let any
data set be evaluated that way: brightness and gamma, low-contrast blue dusk, a warm colour
cast, and smooth-edged cast shadows. Each variant draws its strength (and the shadows their
placement) from a passed generator, so a seed fixes the result.
"""

from __future__ import annotations

import cv2
import numpy as np

VARIANTS: tuple[str, ...] = ("none", "darker", "brighter", "dusk", "warm", "shadows")
"""Names accepted by :func:`apply_variant`."""

_LEVELS = np.arange(256, dtype=np.float64) / 255.0


def variant_rng(seed: int, index: int) -> np.random.Generator:
    """The generator for frame ``index`` of a sequence variant with ``seed``.

    It is child ``index`` of ``SeedSequence(seed)`` (as ``SeedSequence.spawn`` makes it), so
    a frame gets the same variant whatever order frames are processed in.

    Parameters
    ----------
    seed, index : int
        Non-negative.
    """
    if seed < 0 or index < 0:
        raise ValueError(f"seed and index must be non-negative, got {seed}, {index}")
    return np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(int(index),)))


def apply_variant(image_bgr: np.ndarray, name: str, *, rng: np.random.Generator) -> np.ndarray:
    """Apply one photometric variant.

    Parameters
    ----------
    image_bgr : (H, W, 3) uint8 ndarray, BGR
    name : str
        One of :data:`VARIANTS`:

        - ``none``: unchanged copy.
        - ``darker``: gain 0.45-0.65 and gamma 1.1-1.4 (every pixel gets darker).
        - ``brighter``: gamma 1/1.4-1/1.9 and gain 1.0-1.15 (every pixel gets brighter).
        - ``dusk``: contrast 0.45-0.6 around the mean, gain 0.5-0.65, blue +5-12 %,
          red -5-12 %.
        - ``warm``: red +8-20 %, green +0-5 %, blue -10-25 %.
        - ``shadows``: 1-3 dark bands or polygons keeping 35-60 % of the light, edges
          blurred by 1-3 % of the image size, a little bluer inside (skylight).
    rng : numpy.random.Generator
        Source of the variant's strength and of the shadows' placement.

    Returns
    -------
    out : (H, W, 3) uint8 ndarray, BGR
        A new array; the input is not modified.

    Raises
    ------
    ValueError
        Unknown variant name, or not an 8-bit three-channel image.
    """
    if name not in _APPLY:
        raise ValueError(f"unknown photometric variant {name!r}; valid: {', '.join(VARIANTS)}")
    image = np.asarray(image_bgr)
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) uint8 BGR image, got {image.dtype} "
                         f"{image.shape}")
    return _APPLY[name](np.ascontiguousarray(image), rng)


def _channel_lut(curves: np.ndarray) -> np.ndarray:
    """(3, 256) curves in [0, 1] (B, G, R) -> the (1, 256, 3) uint8 table cv2.LUT takes."""
    table = np.clip(np.rint(curves * 255.0), 0, 255).astype(np.uint8)
    return np.ascontiguousarray(table.T[None, :, :])


def _none(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    return image.copy()


def _darker(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    gain, gamma = rng.uniform(0.45, 0.65), rng.uniform(1.1, 1.4)
    # gain < 1 and gamma > 1 both map [0, 1] below the identity: no pixel gets brighter.
    curve = gain * _LEVELS**gamma
    return cv2.LUT(image, _channel_lut(np.stack([curve] * 3)))


def _brighter(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    gamma, gain = rng.uniform(1.4, 1.9), rng.uniform(1.0, 1.15)
    curve = np.minimum(1.0, gain * _LEVELS ** (1.0 / gamma))
    return cv2.LUT(image, _channel_lut(np.stack([curve] * 3)))


def _dusk(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    contrast, gain = rng.uniform(0.45, 0.6), rng.uniform(0.5, 0.65)
    tint = rng.uniform(0.05, 0.12)
    # Contrast shrinks towards the image's own mean so its brightness is set by gain alone.
    pivot = float(image.mean()) / 255.0
    flat = pivot + contrast * (_LEVELS - pivot)
    scale = gain * np.array([1.0 + tint, 1.0, 1.0 - tint])[:, None]  # B, G, R
    return cv2.LUT(image, _channel_lut(flat[None, :] * scale))


def _warm(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    red, green, blue = rng.uniform(0.08, 0.2), rng.uniform(0.0, 0.05), rng.uniform(0.1, 0.25)
    scale = np.array([1.0 - blue, 1.0 + green, 1.0 + red])[:, None]
    return cv2.LUT(image, _channel_lut(_LEVELS[None, :] * scale))


def _shadows(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    h, w = image.shape[:2]
    light = np.ones((h, w), dtype=np.float32)
    canvas = np.zeros((h, w), dtype=np.uint8)
    for _ in range(int(rng.integers(1, 4))):
        keep = np.float32(rng.uniform(0.35, 0.6))
        polygon = _band(rng, w, h) if rng.random() < 0.5 else _blob(rng, w, h)
        canvas[:] = 0
        cv2.fillPoly(canvas, [polygon], 1)
        # Overlapping shadows do not compound: shade is the absence of one light source.
        np.minimum(light, np.where(canvas > 0, keep, np.float32(1.0)), out=light)
    sigma = rng.uniform(0.01, 0.03) * max(h, w)
    light = cv2.GaussianBlur(light, (0, 0), sigmaX=sigma, sigmaY=sigma)
    # Shade is lit by the blue sky only, so blue loses less than red.
    channels = np.stack([light**0.9, light, light**1.05], axis=-1)
    return np.clip(np.rint(image * channels), 0, 255).astype(np.uint8)


def _band(rng: np.random.Generator, w: int, h: int) -> np.ndarray:
    """A straight strip across the image (the shadow of a pole, trunk or wall edge)."""
    centre = rng.uniform(0.0, 1.0, size=2) * (w, h)
    angle = rng.uniform(0.0, np.pi)
    half_width = rng.uniform(0.04, 0.15) * min(w, h)
    along = np.array([np.cos(angle), np.sin(angle)]) * 2.0 * max(w, h)
    across = np.array([-np.sin(angle), np.cos(angle)]) * half_width
    corners = [centre - along - across, centre + along - across,
               centre + along + across, centre - along + across]
    return np.rint(corners).astype(np.int32)


def _blob(rng: np.random.Generator, w: int, h: int) -> np.ndarray:
    """A star-shaped polygon of 3-7 vertices around a random centre (a canopy, a building)."""
    centre = rng.uniform(0.0, 1.0, size=2) * (w, h)
    n = int(rng.integers(3, 8))
    angles = np.sort(rng.uniform(0.0, 2.0 * np.pi, size=n))
    radii = rng.uniform(0.15, 0.45) * min(w, h) * rng.uniform(0.6, 1.0, size=n)
    points = centre + radii[:, None] * np.column_stack([np.cos(angles), np.sin(angles)])
    return np.rint(points).astype(np.int32)


_APPLY = {"none": _none, "darker": _darker, "brighter": _brighter, "dusk": _dusk,
          "warm": _warm, "shadows": _shadows}
