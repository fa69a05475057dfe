"""Shared machinery of the grid features: cells, Gaussian centre weights, histograms.

Every grid feature (Erhard et al. 4.1.1-4.1.3; Weiss et al. 2008, II-A and II-B) splits the
image into a 4x4 grid of subimages, computes an 8-bin histogram per subimage in which each
pixel's vote is weighted by a 2-D Gaussian centred on *its own* subimage, and concatenates
the 16 histograms. Only the per-pixel bin and vote differ between the features, so the grid
geometry is precomputed here once per image shape and the histogram is one ``np.bincount``
over ``cell * n_bins + bin`` indices.

Cells: for an image ``W`` pixels wide, cell column ``c`` holds the columns
``[c * W // 4, (c + 1) * W // 4)`` (rows likewise), so a 320x240 image has 80x60 cells and
other sizes split as evenly as integers allow. Cells are numbered row-major (``row * 4 +
col``), which is also the order of the concatenated histograms.

Weights: the Gaussian of cell ``c`` is centred on the cell's centre ``((x0 + x1 - 1) / 2,
(y0 + y1 - 1) / 2)`` with standard deviations ``sigma_factor`` times the cell's width and
height, peak value 1 (not normalised: all cells of one image get the same total weight up to
the integer split, and the feature vector is normalised as a whole afterwards).
"""

from __future__ import annotations

from functools import cache, cached_property

import numpy as np

GRID: int = 4
"""Subimages per side (Weiss et al. 2008: 4x4)."""

N_BINS: int = 8
"""Histogram bins per subimage (Weiss et al. 2008; Erhard et al. 4.1)."""


def _edges(n: int, grid: int) -> np.ndarray:
    """Integer cell boundaries ``(grid + 1,)`` splitting ``n`` pixels as evenly as possible."""
    return (np.arange(grid + 1) * n) // grid


@cache
def _cell_base(shape: tuple[int, int], step: int) -> np.ndarray:
    """``cell * N_BINS`` for every sampled pixel, raveled: the histogram index base.

    Returns
    -------
    base : (ceil(H/step) * ceil(W/step),) intp ndarray, read-only
    """
    h, w = shape
    row_cell = np.searchsorted(_edges(h, GRID), np.arange(0, h, step), side="right") - 1
    col_cell = np.searchsorted(_edges(w, GRID), np.arange(0, w, step), side="right") - 1
    base = (row_cell[:, None] * GRID + col_cell[None, :]) * N_BINS
    base = base.astype(np.intp).ravel()
    base.flags.writeable = False
    return base


@cache
def _weight_map(shape: tuple[int, int], sigma_factor: float, step: int) -> np.ndarray:
    """Gaussian centre weight of every sampled pixel, raveled.

    Returns
    -------
    weights : (ceil(H/step) * ceil(W/step),) float64 ndarray, read-only
        (float64 because ``np.bincount`` sums in float64 and would convert each time)
    """
    axes = []
    for n in shape:
        edges = _edges(n, GRID)
        pos = np.arange(0, n, step)
        cell = np.searchsorted(edges, pos, side="right") - 1
        size = (edges[cell + 1] - edges[cell]).astype(np.float64)
        centre = (edges[cell] + edges[cell + 1] - 1) / 2.0
        axes.append(np.exp(-0.5 * ((pos - centre) / (sigma_factor * size)) ** 2))
    # separable: the 2-D Gaussian of a cell is the product of its row and column profiles
    weights = (axes[0][:, None] * axes[1][None, :]).ravel()
    weights.flags.writeable = False
    return weights


def grid_histogram(bins: np.ndarray, votes: np.ndarray | None, sigma_factor: float,
                   *, shape: tuple[int, int] | None = None, step: int = 1) -> np.ndarray:
    """Concatenated Gaussian-weighted 8-bin histograms of the 4x4 subimages.

    Parameters
    ----------
    bins : (h, w) integer ndarray
        Bin ``0..7`` of every sampled pixel.
    votes : (h, w) float ndarray or None
        Per-pixel vote (e.g. the gradient magnitude); None votes 1 per pixel.
    sigma_factor : float
        Gaussian standard deviation as a fraction of the cell width and height.
    shape : (H, W), optional
        Size of the full image when ``bins`` holds every ``step``-th row and column of it
        (``bins = full[::step, ::step]``); defaults to ``bins.shape`` with ``step = 1``.
    step : int
        Sampling step of ``bins`` in the full image.

    Returns
    -------
    hist : (128,) float32 ndarray
        Non-negative, summing to 1; all zeros when the image casts no vote (e.g. a WGOH of
        an image without gradients).
    """
    shape = bins.shape if shape is None else shape
    base = _cell_base(shape, step)
    weights = _weight_map(shape, float(sigma_factor), step)
    if base.size != bins.size:
        raise ValueError(f"bins of shape {bins.shape} do not sample an image of {shape} "
                         f"with step {step}")
    index = base + bins.ravel()
    if votes is not None:
        weights = weights * votes.ravel()
    hist = np.bincount(index, weights=weights, minlength=GRID * GRID * N_BINS)
    return normalise_sum(hist)


def normalise_sum(hist: np.ndarray) -> np.ndarray:
    """Scale a non-negative histogram to sum 1 (float32); a histogram without mass stays 0."""
    total = float(hist.sum())
    if total <= 0.0:
        return np.zeros(hist.shape, np.float32)
    return (hist / total).astype(np.float32)


def check_grey(grey: np.ndarray) -> np.ndarray:
    """Validate an 8-bit grey image; return it as a C-contiguous array."""
    grey = np.asarray(grey)
    if grey.dtype != np.uint8 or grey.ndim != 2:
        raise ValueError(f"expected an (H, W) uint8 grey image, got {grey.dtype} {grey.shape}")
    if grey.shape[0] < GRID or grey.shape[1] < GRID:
        raise ValueError(f"image of {grey.shape} is too small for a {GRID}x{GRID} grid")
    return np.ascontiguousarray(grey)


class FrameInputs:
    """Per-frame intermediate arrays shared by several features (see ``extract_many``).

    Parameters
    ----------
    grey : (H, W) uint8 ndarray
    colour : (H, W, 3) uint8 ndarray, BGR, or None when only grey features are wanted

    Attributes
    ----------
    memo : dict
        Intermediate results keyed by the feature module that made them (for instance the
        per-pixel integral-invariant map of a kernel, which ``wgii2_sparse`` can subsample
        instead of recomputing).
    """

    def __init__(self, grey: np.ndarray, colour: np.ndarray | None = None) -> None:
        self.grey = check_grey(grey)
        self.colour = colour
        self.memo: dict = {}

    @cached_property
    def grey_f32(self) -> np.ndarray:
        """(H, W) float32 grey values 0..255 (exact: integers are exact in float32)."""
        return self.grey.astype(np.float32)
