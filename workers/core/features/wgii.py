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
* Arithmetic: grey values are handled in hundredths of a grey value and the ramp half-width
  ``eps * 255`` is rounded to one (exact for 0.098: 24.99). Every difference, clip and sum is
  then an integer below 2**24, exact in float32 whatever the summation order: invariants
  that equal a bin boundary ``k/8`` exactly (very common: ``T = 1/2`` wherever the rotations
  balance) deterministically fall into bin ``k``, and a brightness offset leaves the feature
  bit-identical.
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
_UNITS = 100  # grey values are handled in hundredths, so that eps * 255 = 24.99 is an integer


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
    p1, p2 = tuple(int(v) for v in p1), tuple(int(v) for v in p2)
    return _invariant(FrameInputs(check_grey(grey)), p1, p2, float(eps), int(q), int(step))


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


def _ramp_units(eps: float) -> int:
    """Ramp half-width ``eps * 255`` in hundredths of a grey value (24.99 -> 2499)."""
    return int(round(eps * 255.0 * _UNITS))


def _histogram(inputs: FrameInputs, p1, p2, step: int) -> np.ndarray:
    acc = _accumulated(inputs, p1, p2, EPS, Q, step)
    # 8 T = (4 R q - 4 acc) / (R q) with integers below 2**24: the float32 quotient is an
    # exact integer where 8 T is one, so ties T = k/8 fall into bin k (T = 1 into bin 7)
    scale = np.float32(_ramp_units(EPS) * Q)
    bins = ((scale - acc) * np.float32(4.0) / scale).astype(np.intp)
    np.minimum(bins, _N_BINS - 1, out=bins)
    return grid_histogram(bins, None, SIGMA_FACTOR, shape=inputs.grey.shape, step=step)


def _invariant(inputs: FrameInputs, p1, p2, eps: float, q: int, step: int) -> np.ndarray:
    """``T`` from the accumulated clipped differences: ``1/2 - acc / (2 R q)``."""
    acc = _accumulated(inputs, p1, p2, eps, q, step)
    t = acc * np.float32(-0.5 / (_ramp_units(eps) * q)) + np.float32(0.5)
    return np.clip(t, 0.0, 1.0, out=t)


def _accumulated(inputs: FrameInputs, p1, p2, eps: float, q: int, step: int) -> np.ndarray:
    """``sum_r clip(d_r, -R, R)`` in hundredths of a grey value, memoised per frame."""
    key = ("wgii", p1, p2, eps, q, step)
    if key in inputs.memo:
        return inputs.memo[key]
    dense = inputs.memo.get(("wgii", p1, p2, eps, q, 1))
    if dense is not None:
        # the sparse grid is a subset of the dense one: same values, no recomputation
        acc = dense[::step, ::step]
    else:
        acc = _compute(inputs, rotated_offsets(p1, q), rotated_offsets(p2, q), eps, step)
    inputs.memo[key] = acc
    return acc


def _compute(inputs: FrameInputs, o1: np.ndarray, o2: np.ndarray, eps: float,
             step: int) -> np.ndarray:
    h, w = inputs.grey.shape
    pad = int(max(np.abs(o1).max(), np.abs(o2).max()))
    padded, have = _padded(inputs, pad)
    ramp = np.float32(_ramp_units(eps))
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
        # integers below 2**24 throughout: every sum is exact, whatever the order, and a
        # brightness offset changes no difference at all
        np.subtract(shifted(dx1, dy1), shifted(dx2, dy2), out=diff)
        np.clip(diff, -ramp, ramp, out=diff)
        acc += diff
    return acc


def _padded(inputs: FrameInputs, pad: int) -> tuple[np.ndarray, int]:
    """Grey values x 100, mirrored by at least ``pad`` pixels, shared between kernels."""
    cached = inputs.memo.get("wgii_padded")
    if cached is not None and cached[1] >= pad:
        return cached
    padded = cv2.copyMakeBorder(inputs.grey_f32 * np.float32(_UNITS), pad, pad, pad, pad,
                                cv2.BORDER_REFLECT_101)
    inputs.memo["wgii_padded"] = (padded, pad)
    return padded, pad


def _check_kernel(p1, p2, eps: float, q: int, step: int) -> None:
    if len(p1) != 2 or len(p2) != 2:
        raise ValueError(f"kernel offsets must be (x, y) pairs, got {p1!r} and {p2!r}")
    if not (np.isfinite(eps) and _ramp_units(eps) >= 1):
        raise ValueError(f"eps must be at least 1/100 of a grey value (4e-5), got {eps!r}")
    if int(q) != q or not 1 <= q <= 64:
        raise ValueError(f"q must be an integer in 1..64, got {q!r}")
    if eps > 1:
        raise ValueError(f"eps beyond 1 exceeds the intensity range [0, 1], got {eps!r}")
    if int(step) != step or step < 1:
        raise ValueError(f"step must be a positive integer, got {step!r}")
