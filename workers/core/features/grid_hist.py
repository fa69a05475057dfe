"""Grid greyscale histogram (Erhard et al., Flyphone, section 4.1.1).

The grey scale is divided into eight bins of 32 grey values each (``bin = grey // 32``), for
robustness to illumination changes; the image is split into 4x4 subimages with one histogram
each, and a pixel's vote is weighted by a Gaussian centred on its subimage so that pixels
near the centre, which stay in the same subimage under small translations and rotations,
count more.

Erhard et al. do not give the Gaussian's width; the WGOH value of the same group (standard
deviation 0.5 x the subimage's width and height, Weiss et al. 2008 II-A) is used.
"""

from __future__ import annotations

import numpy as np

from ._grid import FrameInputs, check_grey, grid_histogram

SIGMA_FACTOR: float = 0.5
"""Gaussian standard deviation / subimage size (not stated in Flyphone; WGOH's value)."""

GREY_PER_BIN: int = 32
"""Grey values per bin: 256 / 8 (Erhard et al. 4.1.1)."""


def grid_hist(grey: np.ndarray) -> np.ndarray:
    """Grid greyscale histogram of a grey image (Erhard et al. 4.1.1).

    Parameters
    ----------
    grey : (H, W) uint8 ndarray

    Returns
    -------
    feature : (128,) float32 ndarray
        16 concatenated 8-bin histograms (cells row-major, bin ``k`` = grey values
        ``32k .. 32k + 31``), non-negative, summing to 1.
    """
    return _grid_hist_inputs(FrameInputs(check_grey(grey)))


def _grid_hist_inputs(inputs: FrameInputs) -> np.ndarray:
    # a right shift of uint8 by 5 is the division by 32, without leaving 8 bits
    bins = np.right_shift(inputs.grey, 5)
    return grid_histogram(bins, None, SIGMA_FACTOR)
