"""Hue histogram of the HSI colour space (Li et al., eq. 4), the hierarchical coarse stage.

Li et al. eq. 4 gives the HSI hue as

    H = arccos( ((R - G) + (R - B)) / (2 sqrt((R - G)^2 + (R - B)(G - B))) )

(the printed equation squares ``(G - B)`` inside the root by a typesetting slip; the
standard HSI formula, used here, does not). The arccos only covers [0, pi]; as in the
standard HSI conversion, ``H = 2 pi - H`` where ``B > G``, so hue spans the full circle and
e.g. yellow and magenta (both 60 degrees from red) stay apart. The same angle is
``atan2(sqrt(3) (G - B), 2R - G - B)``, which is how it is computed here, free of the
division by zero at grey pixels.

Choices the paper leaves open, and what is used here:

* Bins: 32 bins of 11.25 degrees over [0, 360), bin 0 starting at red. Coarse enough that the
  few-degree hue shifts of white balance and JPEG chroma subsampling mostly stay in one bin,
  fine enough to keep apart the colours of an outdoor scene (sky, foliage, grass, brick).
* Grey pixels: hue is undefined where R = G = B and meaningless where the colour is nearly
  grey, as a tiny chroma turns sensor noise into any hue. Each pixel therefore votes with its
  chroma, Li's ``S = max(R, G, B) - min(R, G, B)``: grey pixels vote 0, near-grey and dark
  pixels, whose hue is noise, vote little (a saturation-weighted hue histogram). Scaling
  R, G, B by a common factor scales every vote alike, so the normalised histogram is
  invariant to intensity scaling, with no threshold for pixels to cross.
* An image without any colour (all grey) gives the all-zero vector.

The histogram is compared with Euclidean distance (Li et al. eq. 5): measure ``"l2"`` of
:mod:`workers.core.measures`, which scales both vectors to unit L2 norm first.
"""

from __future__ import annotations

from functools import cache

import cv2
import numpy as np

from ._grid import normalise_sum

N_HUE_BINS: int = 32
"""Hue bins over the full circle (11.25 degrees each)."""


def hue_hist(bgr: np.ndarray) -> np.ndarray:
    """Chroma-weighted histogram of the HSI hue (Li et al. eq. 4).

    Parameters
    ----------
    bgr : (H, W, 3) uint8 ndarray
        Colour image in OpenCV's BGR channel order.

    Returns
    -------
    feature : (32,) float32 ndarray
        Bin ``k`` holds hues in ``[11.25 k, 11.25 (k + 1))`` degrees (0 = red, 120 = green,
        240 = blue); non-negative, summing to 1, or all zeros for an image without colour.
    """
    bgr = np.asarray(bgr)
    if bgr.dtype != np.uint8 or bgr.ndim != 3 or bgr.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) uint8 BGR image, got {bgr.dtype} {bgr.shape}")
    channels = cv2.split(np.ascontiguousarray(bgr))
    b, g, r = (c.astype(np.int32) for c in channels)
    # the hue is a function of the integer pair (G - B, 2R - G - B): one table look-up
    key = (g - b + 255) * _N_X + (2 * r - g - b + 510)
    chroma = cv2.subtract(cv2.max(cv2.max(*channels[:2]), channels[2]),
                          cv2.min(cv2.min(*channels[:2]), channels[2]))
    hist = np.bincount(np.take(_bin_table(), key.ravel()),
                       weights=chroma.ravel().astype(np.float64), minlength=N_HUE_BINS)
    return normalise_sum(hist)


_N_X = 1021  # values of 2R - G - B: -510 .. 510


@cache
def _bin_table() -> np.ndarray:
    """Hue bin of every ``(G - B, 2R - G - B)`` pair, raveled: ``(511 * 1021,)`` uint8."""
    y = np.sqrt(3.0) * np.arange(-255, 256, dtype=np.float64)[:, None]
    x = np.arange(-510, 511, dtype=np.float64)[None, :]
    table = hue_bin(np.arctan2(y, x)).astype(np.uint8).ravel()
    table.flags.writeable = False
    return table


def hue_bin(hue: np.ndarray | float) -> np.ndarray:
    """Bin index of a hue angle in radians (any real angle; wrapped to [0, 2 pi))."""
    return np.floor(np.mod(hue, 2.0 * np.pi) * (N_HUE_BINS / (2.0 * np.pi))).astype(
        np.intp) % N_HUE_BINS
