"""Small synthetic images with texture enough for SIFT and ORB, for tests of features and
map packing."""

from __future__ import annotations

import cv2
import numpy as np


def discs(seed: int) -> np.ndarray:
    """A 320x240 BGR scene of coloured discs over a smooth random background."""
    rng = np.random.default_rng(seed)
    img = cv2.resize(rng.integers(0, 256, (30, 40, 3), dtype=np.uint8), (320, 240),
                     interpolation=cv2.INTER_CUBIC)
    for _ in range(60):
        c = (int(rng.integers(0, 320)), int(rng.integers(0, 240)))
        cv2.circle(img, c, int(rng.integers(3, 12)),
                   tuple(int(v) for v in rng.integers(0, 256, 3)), -1)
    return img


def strokes(seed: int) -> np.ndarray:
    """A scene unlike :func:`discs`: straight coloured strokes on black."""
    rng = np.random.default_rng(seed)
    img = np.zeros((240, 320, 3), np.uint8)
    for _ in range(40):
        cv2.line(img, (int(rng.integers(0, 320)), 0), (int(rng.integers(0, 320)), 239),
                 tuple(int(v) for v in rng.integers(0, 256, 3)), int(rng.integers(1, 6)))
    return img
