"""Weighted Grid Integral Invariants (WGII).

Weiss et al. 2008, section II-B (and their ICVS 2007 paper); Erhard et al. 4.1.3; the
relational kernel of Siggelkow 2002. For every pixel ``x`` a kernel compares two neighbours
``x + g_r p1`` and ``x + g_r p2``, where ``g_r`` is the rotation by ``2 pi r / q``; the
invariant of the pixel is the mean over the ``q`` rotations (Erhard et al. eq. 1 before the
sum over pixels)::

    T(x) = 1/q * sum_r rel( I(x + g_r p1) - I(x + g_r p2) )

with intensities ``I`` scaled to [0, 1] and Siggelkow's relational function, a ramp of width
``2 eps``::

    rel(d) = 1                    if d < -eps
           = (eps - d) / (2 eps)  if -eps <= d <= eps
           = 0                    if d > eps

so ``T(x)`` lies in [0, 1] and is 0.5 on flat ground. The image is split into 4x4 subimages
with an 8-bin histogram of ``T`` each (bin ``k`` holds ``[k/8, (k+1)/8)``, with ``T = 1`` in
bin 7), a pixel's vote weighted by a Gaussian centred on its subimage with standard
deviations 0.25 x the subimage's width and height, and the histograms are concatenated.

Choices the papers leave open, and what is used here:

* Offsets ``p = (x, y)`` are in pixels, x right and y down; ``g_r p`` is rounded to the
  nearest pixel (no interpolation), which keeps every rotation a plain array shift.
* Border: the image is mirrored without repeating the edge pixel (OpenCV's
  ``BORDER_REFLECT_101``), so kernels near the border compare real image content instead of
  an invented constant that would read as an edge.
* ``wgii2`` (Flyphone) uses the same ``eps``, ``q`` and Gaussian as ``wgii``; its 256-d vector
  is the two kernels' 128-d histograms concatenated, each half summing to 0.5.
* Sparse evaluation (``wgii2_sparse``; Flyphone computes the invariants "in every fourth
  randomized pixel location"): here the invariant is evaluated on the pixels with even row
  *and* even column index, i.e. one fixed pixel of each 2x2 block, a quarter of the pixels,
  spread evenly over the image. A fixed pattern rather than a random one keeps map and query
  features on the same sampling grid and the feature a pure function of the image. Kernel
  offsets still read the full-resolution image.

Invariances: a uniform brightness offset changes no difference ``I(p1) - I(p2)`` and so no
invariant (as long as no pixel saturates); a rotation of the image about a pixel permutes
the rotations up to the ``2 pi / q`` discretisation.
"""

from __future__ import annotations

import cv2
import numpy as np

from ._grid import FrameInputs, check_grey, grid_histogram

P1: tuple[int, int] = (10, 0)
P2: tuple[int, int] = (0, 20)
EPS: float = 0.098
Q: int = 10
"""Kernel of Weiss et al. 2008 II-B: offsets p1, p2 (pixels), ramp eps, rotations q."""

KERNELS_2: tuple[tuple[tuple[int, int], tuple[int, int]], ...] = (((2, 0), (0, 3)),
                                                                 ((5, 0), (0, 10)))
"""The two kernels (p1, p2) of the 256-d WGII of Erhard et al. 4.1.3."""

SIGMA_FACTOR: float = 0.25
"""Gaussian standard deviation / subimage size (Weiss et al. 2008, II-B)."""

SPARSE_STEP: int = 2
"""``wgii2_sparse`` evaluates every 2nd row and every 2nd column: a quarter of the pixels."""

_N_BINS = 8


def rotated_offsets(p: tuple[int, int], q: int) -> np.ndarray:
    """Offset ``p`` rotated by ``2 pi r / q`` for ``r = 0 .. q-1``, rounded to pixels.

    Returns
    -------
    offsets : (q, 2) intp ndarray
        ``(dx, dy)`` per rotation.
    """
    phi = 2.0 * np.pi * np.arange(q) / q
    c, s = np.cos(phi), np.sin(phi)
    x, y = p
    return np.rint(np.stack([x * c - y * s, x * s + y * c], axis=1)).astype(np.intp)


def integral_invariant(grey: np.ndarray, p1: tuple[int, int] = P1, p2: tuple[int, int] = P2,
                       eps: float = EPS, q: int = Q, *, step: int = 1) -> np.ndarray:
    """Per-pixel relational-kernel integral invariant ``T(x)`` (module docstring).

    Parameters
    ----------
    grey : (H, W) uint8 ndarray
    p1, p2 : (int, int)
        Kernel offsets ``(x, y)`` in pixels.
    eps : float
        Half-width of the relational ramp on intensities scaled to [0, 1].
    q : int
        Number of rotations.
    step : int
        Evaluate every ``step``-th row and column only (``step = 2``: the sparse variant).

    Returns
    -------
    invariant : (ceil(H/step), ceil(W/step)) float32 ndarray
        Values in [0, 1]; 0.5 where the neighbourhood is flat.
    """
    _check_kernel(p1, p2, eps, q, step)
    return _invariant(FrameInputs(check_grey(grey)), tuple(p1), tuple(p2), eps, q, step)


def wgii(grey: np.ndarray) -> np.ndarray:
    """WGII feature of a grey image (Weiss et al. 2008, II-B).

    Parameters
    ----------
    grey : (H, W) uint8 ndarray

    Returns
    -------
    feature : (128,) float32 ndarray
        16 concatenated 8-bin histograms of the invariant (cells row-major),
        non-negative, summing to 1.
    """
    return _wgii_inputs(FrameInputs(check_grey(grey)))


def wgii2(grey: np.ndarray) -> np.ndarray:
    """Two-kernel WGII of Erhard et al. 4.1.3, evaluated at every pixel.

    Returns
    -------
    feature : (256,) float32 ndarray
        Kernel (2,0)/(0,3)'s 128 bins, then kernel (5,0)/(0,10)'s; each half sums to 0.5.
    """
    return _wgii2_inputs(FrameInputs(check_grey(grey)), 1)


def wgii2_sparse(grey: np.ndarray) -> np.ndarray:
    """:func:`wgii2` evaluated at one pixel of every 2x2 block (module docstring).

    Returns
    -------
    feature : (256,) float32 ndarray
    """
    return _wgii2_inputs(FrameInputs(check_grey(grey)), SPARSE_STEP)


def _wgii_inputs(inputs: FrameInputs) -> np.ndarray:
    return _histogram(inputs, P1, P2, 1)


def _wgii2_inputs(inputs: FrameInputs, step: int) -> np.ndarray:
    halves = [_histogram(inputs, p1, p2, step) for p1, p2 in KERNELS_2]
    return np.concatenate(halves) / np.float32(len(halves))


def _wgii2_sparse_inputs(inputs: FrameInputs) -> np.ndarray:
    return _wgii2_inputs(inputs, SPARSE_STEP)


def _histogram(inputs: FrameInputs, p1, p2, step: int) -> np.ndarray:
    t = _invariant(inputs, p1, p2, EPS, Q, step)
    # T = 1 exactly would be bin 8: it belongs to the top bin
    bins = np.minimum((t * np.float32(_N_BINS)).astype(np.intp), _N_BINS - 1)
    return grid_histogram(bins, None, SIGMA_FACTOR, shape=inputs.grey.shape, step=step)


def _invariant(inputs: FrameInputs, p1, p2, eps: float, q: int, step: int) -> np.ndarray:
    key = ("wgii", p1, p2, eps, q, step)
    dense = inputs.memo.get(("wgii", p1, p2, eps, q, 1))
    if key in inputs.memo:
        return inputs.memo[key]
    if dense is not None:
        # the sparse grid is a subset of the dense one: same values, no recomputation
        t = dense[::step, ::step]
    else:
        t = _compute_invariant(inputs, rotated_offsets(p1, q), rotated_offsets(p2, q),
                               eps, step)
    inputs.memo[key] = t
    return t


def _compute_invariant(inputs: FrameInputs, o1: np.ndarray, o2: np.ndarray, eps: float,
                       step: int) -> np.ndarray:
    h, w = inputs.grey.shape
    pad = int(max(np.abs(o1).max(), np.abs(o2).max()))
    padded, have = _padded(inputs, pad)
    ramp = np.float32(eps * 255.0)  # eps in grey values
    hs, ws = (h + step - 1) // step, (w + step - 1) // step
    acc = np.zeros((hs, ws), np.float32)
    diff = np.empty_like(acc)
    # the sampled pixels' neighbours at one offset all lie in one phase of the step grid;
    # contiguous copies of the phases make every shift a contiguous slice
    phases: dict[tuple[int, int], np.ndarray] = {}

    def shifted(dx: int, dy: int) -> np.ndarray:
        y, x = have + dy, have + dx
        if step == 1:
            return padded[y:y + h, x:x + w]
        phase = (y % step, x % step)
        if phase not in phases:
            phases[phase] = np.ascontiguousarray(padded[phase[0]::step, phase[1]::step])
        return phases[phase][y // step:y // step + hs, x // step:x // step + ws]

    for (dx1, dy1), (dx2, dy2) in zip(o1, o2, strict=True):
        # differences of integer grey values are exact, so the clip (the ramp) and the sum
        # do not depend on a brightness offset at all
        np.subtract(shifted(dx1, dy1), shifted(dx2, dy2), out=diff)
        np.clip(diff, -ramp, ramp, out=diff)
        acc += diff
    # rel = 1/2 - clip(d, -ramp, ramp) / (2 ramp), averaged over the q rotations
    t = acc * np.float32(-0.5 / (ramp * len(o1))) + np.float32(0.5)
    return np.clip(t, 0.0, 1.0, out=t)


def _padded(inputs: FrameInputs, pad: int) -> tuple[np.ndarray, int]:
    """The grey image mirrored by at least ``pad`` pixels, shared between kernels."""
    cached = inputs.memo.get("wgii_padded")
    if cached is not None and cached[1] >= pad:
        return cached
    padded = cv2.copyMakeBorder(inputs.grey_f32, pad, pad, pad, pad, cv2.BORDER_REFLECT_101)
    inputs.memo["wgii_padded"] = (padded, pad)
    return padded, pad


def _check_kernel(p1, p2, eps: float, q: int, step: int) -> None:
    if len(p1) != 2 or len(p2) != 2:
        raise ValueError(f"kernel offsets must be (x, y) pairs, got {p1!r} and {p2!r}")
    if not (eps > 0 and np.isfinite(eps)):
        raise ValueError(f"eps must be positive and finite, got {eps!r}")
    if int(q) != q or q < 1:
        raise ValueError(f"q must be a positive integer, got {q!r}")
    if int(step) != step or step < 1:
        raise ValueError(f"step must be a positive integer, got {step!r}")
