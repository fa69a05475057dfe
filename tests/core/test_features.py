"""Global features: hand-computed cases, slow per-pixel references, invariances, registry."""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from vloc.workers.core.features import (
    FEATURE_NAMES,
    GLOBAL_FEATURES,
    extract,
    extract_many,
    get_feature,
    grid_hist,
    hue_hist,
    integral_invariant,
    wgii,
    wgii2,
    wgii2_sparse,
    wgoh,
)
from vloc.workers.core.features.wgii import rotated_offsets
from vloc.workers.core.image import Frame, prepare

H, W = 48, 64  # 4x4 cells of 12x16 pixels


@pytest.fixture(scope="module")
def random_grey() -> np.ndarray:
    return np.random.default_rng(7).integers(0, 256, (H, W), dtype=np.uint8)


@pytest.fixture(scope="module")
def smooth_grey() -> np.ndarray:
    """Random image with structure at several scales (blurred noise plus a gradient)."""
    import cv2

    rng = np.random.default_rng(11)
    noise = rng.normal(0.0, 1.0, (H, W)).astype(np.float32)
    blurred = cv2.GaussianBlur(noise, (0, 0), 3.0)
    img = 100 + 60 * blurred / blurred.std() + np.linspace(-20, 20, W)[None, :]
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


# --- slow, obvious references ---------------------------------------------------------------

def _cell_of(i: int, n: int) -> int:
    return max(c for c in range(4) if c * n // 4 <= i)


def _gauss_weight(y: int, x: int, shape, sigma_factor: float) -> float:
    w = 1.0
    for pos, n in ((y, shape[0]), (x, shape[1])):
        c = _cell_of(pos, n)
        lo, hi = c * n // 4, (c + 1) * n // 4
        centre = (lo + hi - 1) / 2
        w *= math.exp(-0.5 * ((pos - centre) / (sigma_factor * (hi - lo))) ** 2)
    return w


def _ref_grid(votes, shape, sigma_factor, step=1) -> np.ndarray:
    """votes: iterable of (y, x, bin, vote) in full-image coordinates."""
    hist = np.zeros(128)
    for y, x, b, v in votes:
        cell = _cell_of(y, shape[0]) * 4 + _cell_of(x, shape[1])
        hist[cell * 8 + b] += v * _gauss_weight(y, x, shape, sigma_factor)
    return hist / hist.sum() if hist.sum() > 0 else hist


def _ref_grid_hist(grey) -> np.ndarray:
    h, w = grey.shape
    return _ref_grid(((y, x, int(grey[y, x]) // 32, 1.0) for y in range(h) for x in range(w)),
                     grey.shape, 0.5)


def _ref_wgoh(grey) -> np.ndarray:
    g = grey.astype(float)
    h, w = g.shape

    def at(y, x):
        return g[min(max(y, 0), h - 1), min(max(x, 0), w - 1)]

    votes = []
    for y in range(h):
        for x in range(w):
            gx = at(y, x + 1) - at(y, x - 1)
            gy = at(y + 1, x) - at(y - 1, x)
            theta = math.atan2(gy, gx)
            b = math.floor((theta + math.pi / 8) / (math.pi / 4)) % 8
            votes.append((y, x, b, math.hypot(gx, gy)))
    return _ref_grid(votes, grey.shape, 0.5)


def _reflect(i: int, n: int) -> int:
    period = 2 * (n - 1)
    i %= period
    return period - i if i >= n else i


def _ref_invariant(grey, p1, p2, eps, q, step=1) -> list[list[Fraction]]:
    """T per sampled pixel, exactly (fractions), with eps * 255 in hundredths of a grey."""
    h, w = grey.shape
    ramp = Fraction(round(eps * 25500), 100 * 255)
    offsets = []
    for r in range(q):
        phi = 2 * math.pi * r / q
        c, s = math.cos(phi), math.sin(phi)
        offsets.append(tuple((round(px * c - py * s), round(px * s + py * c))
                             for px, py in (p1, p2)))
    out = []
    for y in range(0, h, step):
        row = []
        for x in range(0, w, step):
            total = Fraction(0)
            for (dx1, dy1), (dx2, dy2) in offsets:
                d = Fraction(int(grey[_reflect(y + dy1, h), _reflect(x + dx1, w)])
                             - int(grey[_reflect(y + dy2, h), _reflect(x + dx2, w)]), 255)
                total += 1 if d < -ramp else 0 if d > ramp else (ramp - d) / (2 * ramp)
            row.append(total / q)
        out.append(row)
    return out


def _ref_wgii(grey, p1=(10, 0), p2=(0, 20), step=1) -> np.ndarray:
    t = _ref_invariant(grey, p1, p2, 0.098, 10, step)
    votes = [(y * step, x * step, min(math.floor(v * 8), 7), 1.0)
             for y, row in enumerate(t) for x, v in enumerate(row)]
    return _ref_grid(votes, grey.shape, 0.25, step)


def _ref_hue_hist(bgr) -> np.ndarray:
    hist = np.zeros(32)
    for b, g, r in bgr.reshape(-1, 3).astype(int):
        chroma = max(r, g, b) - min(r, g, b)
        if chroma == 0:
            continue
        # Li et al. eq. 4 with the standard HSI reflection for B > G
        cos_h = ((r - g) + (r - b)) / (2 * math.sqrt((r - g) ** 2 + (r - b) * (g - b)))
        hue = math.acos(min(1.0, max(-1.0, cos_h)))
        if b > g:
            hue = 2 * math.pi - hue
        hist[int(hue / (2 * math.pi / 32)) % 32] += chroma
    return hist / hist.sum() if hist.sum() > 0 else hist


# --- hand-computed cases ----------------------------------------------------------------------

def _cells(feature: np.ndarray) -> np.ndarray:
    """(16, 8) view: one row per cell, row-major."""
    return feature.reshape(16, 8)


def test_grid_hist_constant_image_puts_all_mass_in_bin_3():
    cells = _cells(grid_hist(np.full((H, W), 100, np.uint8)))
    expected = np.zeros((16, 8))
    expected[:, 3] = 1 / 16
    np.testing.assert_allclose(cells, expected, atol=1e-7)


def test_grid_hist_half_black_half_white():
    grey = np.zeros((H, W), np.uint8)
    grey[:, W // 2:] = 255
    cells = _cells(grid_hist(grey)).reshape(4, 4, 8)
    np.testing.assert_allclose(cells[:, :2, 0], 1 / 16, atol=1e-7)
    np.testing.assert_allclose(cells[:, 2:, 7], 1 / 16, atol=1e-7)
    assert cells.sum() == pytest.approx(1.0, abs=1e-6)


def test_grid_hist_centre_pixels_weigh_more_than_border_pixels():
    grey = np.zeros((H, W), np.uint8)
    grey[6, 8] = 255   # centre of cell 0 (rows 0..11, columns 0..15, centre 5.5/7.5)
    grey[0, 16] = 255  # corner of cell 1
    cells = _cells(grid_hist(grey))
    # sigma = 0.5 x (12, 16): offsets (0.5, 0.5) from the centre against (5.5, 7.5)
    centre = math.exp(-0.5 * ((0.5 / 6) ** 2 + (0.5 / 8) ** 2))
    corner = math.exp(-0.5 * ((5.5 / 6) ** 2 + (7.5 / 8) ** 2))
    assert cells[0, 7] / cells[1, 7] == pytest.approx(centre / corner, rel=1e-5)
    assert centre / corner > 2


def test_wgoh_constant_image_is_all_zero():
    f = wgoh(np.full((H, W), 77, np.uint8))
    assert f.shape == (128,) and f.dtype == np.float32
    assert not f.any()


@pytest.mark.parametrize(("left", "right", "axis", "bin_"),
                         [(50, 150, 1, 0), (150, 50, 1, 4), (50, 150, 0, 2), (150, 50, 0, 6)])
def test_wgoh_step_edge_puts_all_mass_in_one_bin_of_the_crossed_cells(left, right, axis, bin_):
    grey = np.full((H, W), left, np.uint8)
    if axis == 1:   # vertical edge between columns 39 and 40: cell column 2 (32..47)
        grey[:, 40:] = right
        crossed = [(r, 2) for r in range(4)]
    else:           # horizontal edge between rows 29 and 30: cell row 2 (24..35)
        grey[30:, :] = right
        crossed = [(2, c) for c in range(4)]
    cells = _cells(wgoh(grey)).reshape(4, 4, 8)
    expected = np.zeros((4, 4, 8))
    for r, c in crossed:
        expected[r, c, bin_] = 1 / 4
    np.testing.assert_allclose(cells, expected, atol=1e-7)


def test_wgoh_diagonal_ramp_is_bin_1_everywhere_including_borders():
    y, x = np.mgrid[0:H, 0:W]
    cells = _cells(wgoh((x + y).astype(np.uint8)))
    assert cells[:, 1].sum() == pytest.approx(1.0, abs=1e-6)
    assert (cells[:, 1] > 0).all()
    assert not np.delete(cells, 1, axis=1).any()


def test_wgii_constant_image_puts_all_mass_in_bin_4():
    for feature in (wgii, wgii2, wgii2_sparse):
        f = feature(np.full((H, W), 200, np.uint8))
        bins = f.reshape(-1, 8)
        assert bins[:, 4].sum() == pytest.approx(1.0, abs=1e-6)
        np.testing.assert_allclose(bins[:, 4], 1 / len(bins), rtol=1e-5)


def test_rotated_offsets_of_weiss_kernel():
    o1 = rotated_offsets((10, 0), 10)
    assert o1.shape == (10, 2)
    assert tuple(o1[0]) == (10, 0) and tuple(o1[5]) == (-10, 0)
    # 36 degrees: (10 cos 36, 10 sin 36) = (8.09, 5.88)
    assert tuple(o1[1]) == (8, 6)
    assert tuple(rotated_offsets((0, 20), 10)[1]) == (-12, 16)  # (-11.76, 16.18)


def test_integral_invariant_single_bright_pixel_by_hand():
    """p1 = (1, 0), p2 = (0, 2), q = 4 around one bright pixel B on black.

    A pixel whose p1 neighbour (radius 1) is B sees d = +1 there (rel 0) and d = 0 in the
    other three rotations (rel 1/2): T = 3/8. A pixel whose p2 neighbour (radius 2) is B sees
    d = -1 (rel 1) once: T = 5/8. Everything else is flat: T = 1/2.
    """
    grey = np.zeros((16, 16), np.uint8)
    grey[8, 8] = 255
    t = integral_invariant(grey, (1, 0), (0, 2), 0.098, 4)
    expected = np.full((16, 16), 0.5)
    for dy, dx in ((0, 1), (1, 0), (0, -1), (-1, 0)):
        expected[8 - dy, 8 - dx] = 3 / 8
        expected[8 - 2 * dy, 8 - 2 * dx] = 5 / 8
    np.testing.assert_allclose(t, expected, atol=1e-6)


def test_integral_invariant_ramp_inside_eps():
    grey = np.zeros((16, 16), np.uint8)
    grey[8, 8] = 10  # d = 10/255 = 0.039 < eps: on the ramp, rel = (eps - d) / (2 eps)
    t = integral_invariant(grey, (1, 0), (0, 2), 0.098, 4)
    rel = (0.098 - 10 / 255) / (2 * 0.098)
    assert t[8, 7] == pytest.approx((rel + 1.5) / 4, abs=1e-6)
    assert t[8, 6] == pytest.approx((1 - rel + 1.5) / 4, abs=1e-6)


# --- fast against slow reference --------------------------------------------------------------

def test_grid_hist_matches_reference(random_grey):
    np.testing.assert_allclose(grid_hist(random_grey), _ref_grid_hist(random_grey), atol=1e-6)


def test_wgoh_matches_reference(random_grey, smooth_grey):
    for grey in (random_grey, smooth_grey):
        np.testing.assert_allclose(wgoh(grey), _ref_wgoh(grey), atol=1e-6)


@pytest.mark.parametrize("step", [1, 2])
def test_integral_invariant_matches_reference(smooth_grey, step):
    for p1, p2 in (((10, 0), (0, 20)), ((2, 0), (0, 3))):
        fast = integral_invariant(smooth_grey, p1, p2, 0.098, 10, step=step)
        slow = np.array(_ref_invariant(smooth_grey, p1, p2, 0.098, 10, step), dtype=float)
        np.testing.assert_allclose(fast, slow, atol=1e-6)


def test_wgii_matches_reference(random_grey, smooth_grey):
    for grey in (random_grey, smooth_grey):
        np.testing.assert_allclose(wgii(grey), _ref_wgii(grey), atol=1e-6)


@pytest.mark.parametrize(("feature", "step"), [(wgii2, 1), (wgii2_sparse, 2)])
def test_wgii2_matches_reference(smooth_grey, feature, step):
    halves = [_ref_wgii(smooth_grey, (2, 0), (0, 3), step),
              _ref_wgii(smooth_grey, (5, 0), (0, 10), step)]
    np.testing.assert_allclose(feature(smooth_grey), np.concatenate(halves) / 2, atol=1e-6)


def test_sparse_invariant_is_the_dense_one_on_even_rows_and_columns(smooth_grey):
    dense = integral_invariant(smooth_grey, (5, 0), (0, 10))
    sparse = integral_invariant(smooth_grey, (5, 0), (0, 10), step=2)
    np.testing.assert_array_equal(sparse, dense[::2, ::2])


def test_hue_hist_matches_reference():
    bgr = np.random.default_rng(3).integers(0, 256, (H, W, 3), dtype=np.uint8)
    bgr[:10] = bgr[:10, :, :1]  # some grey pixels (hue undefined)
    np.testing.assert_allclose(hue_hist(bgr), _ref_hue_hist(bgr), atol=1e-6)


# --- hue histogram by hand --------------------------------------------------------------------

@pytest.mark.parametrize(("bgr", "bin_"), [
    ((0, 0, 200), 0),       # red, hue 0
    ((0, 200, 200), 5),     # yellow, 60 degrees: 60 / 11.25 = 5.3
    ((0, 200, 0), 10),      # green, 120: 10.7
    ((200, 200, 0), 16),    # cyan, 180: 16.0
    ((200, 0, 0), 21),      # blue, 240: 21.3
    ((200, 0, 200), 26),    # magenta, 300: 26.7 (apart from yellow: B > G reflection)
])
def test_hue_hist_pure_colours_in_bgr_order(bgr, bin_):
    image = np.empty((8, 8, 3), np.uint8)
    image[:] = bgr
    expected = np.zeros(32)
    expected[bin_] = 1.0
    np.testing.assert_allclose(hue_hist(image), expected, atol=1e-7)


def test_hue_hist_grey_pixels_do_not_vote_and_chroma_weighs():
    image = np.zeros((8, 12, 3), np.uint8)
    image[:, :4] = (0, 0, 200)    # red, chroma 200
    image[:, 4:8] = (0, 100, 0)   # green, chroma 100
    image[:, 8:] = (90, 90, 90)   # grey, chroma 0
    f = hue_hist(image)
    assert f[0] == pytest.approx(2 / 3) and f[10] == pytest.approx(1 / 3)
    assert not hue_hist(np.full((8, 8, 3), 128, np.uint8)).any()


# --- invariances ------------------------------------------------------------------------------

def test_wgii_and_wgoh_unchanged_by_a_brightness_offset(smooth_grey):
    base = (smooth_grey.astype(int) * 200 // 255).astype(np.uint8)  # no saturation at +50
    brighter = base + np.uint8(50)
    for feature in (wgii, wgii2, wgii2_sparse, wgoh):
        # equal up to float32 round-off in the final normalisation
        np.testing.assert_allclose(feature(brighter), feature(base), rtol=1e-6, atol=1e-9)


def test_wgoh_unchanged_by_a_gain(smooth_grey):
    base = smooth_grey // 2
    np.testing.assert_allclose(wgoh(base * 2), wgoh(base), atol=1e-7)


def test_hue_hist_unchanged_by_intensity_scaling():
    bgr = np.random.default_rng(5).integers(0, 128, (H, W, 3), dtype=np.uint8)
    np.testing.assert_allclose(hue_hist(bgr * 2), hue_hist(bgr), atol=1e-7)


def test_invariant_map_follows_a_half_turn_of_the_image(smooth_grey):
    """q = 10 contains the 180-degree rotation, and rounding is symmetric under negation."""
    t = integral_invariant(smooth_grey)
    np.testing.assert_allclose(integral_invariant(smooth_grey[::-1, ::-1].copy()),
                               t[::-1, ::-1], atol=1e-6)


def test_invariant_map_follows_a_quarter_turn_with_q_4(smooth_grey):
    t = integral_invariant(smooth_grey, (3, 0), (0, 5), 0.098, 4)
    rotated = integral_invariant(np.rot90(smooth_grey).copy(), (3, 0), (0, 5), 0.098, 4)
    np.testing.assert_allclose(rotated, np.rot90(t), atol=1e-6)


# --- registry ---------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def frame() -> Frame:
    rng = np.random.default_rng(1)
    colour = rng.integers(0, 256, (60, 80, 3), dtype=np.uint8)
    return prepare(colour, (80, 60))


def test_registry_lists_every_feature_with_its_true_dimension(frame):
    assert FEATURE_NAMES == ("grid_hist", "wgoh", "wgii", "wgii2", "wgii2_sparse", "hue_hist")
    for name, spec in GLOBAL_FEATURES.items():
        f = extract(name, frame)
        assert spec.name == name
        assert f.shape == (spec.dim,) and f.dtype == np.float32
        assert f.min() >= 0 and f.sum() == pytest.approx(1.0, abs=1e-5)
        np.testing.assert_array_equal(spec.fn(frame), f)


def test_registry_wraps_the_array_functions(frame):
    array_fns = {"grid_hist": grid_hist, "wgoh": wgoh, "wgii": wgii, "wgii2": wgii2,
                 "wgii2_sparse": wgii2_sparse}
    for name, fn in array_fns.items():
        np.testing.assert_array_equal(extract(name, frame), fn(frame.grey))
    np.testing.assert_array_equal(extract("hue_hist", frame), hue_hist(frame.colour))


def test_extract_many_equals_one_by_one_in_any_order(frame):
    names = ("wgii2_sparse", "wgii2", "hue_hist", "wgii", "wgoh", "grid_hist", "wgii2")
    many = extract_many(names, frame)
    assert list(many) == ["wgii2_sparse", "wgii2", "hue_hist", "wgii", "wgoh", "grid_hist"]
    for name, f in many.items():
        np.testing.assert_array_equal(f, extract(name, frame))
    shared = extract_many(["wgii2", "wgii2_sparse"], frame)  # sparse from the dense map
    np.testing.assert_array_equal(shared["wgii2_sparse"], extract("wgii2_sparse", frame))


def test_unknown_feature_name_lists_the_valid_ones(frame):
    with pytest.raises(ValueError, match="wgoh") as info:
        get_feature("sift")
    assert "sift" in str(info.value)
    with pytest.raises(ValueError):
        extract("nope", frame)
    with pytest.raises(ValueError):
        extract_many(["wgoh", "nope"], frame)


def test_bad_images_are_refused():
    with pytest.raises(ValueError):
        wgoh(np.zeros((H, W), np.float32))
    with pytest.raises(ValueError):
        wgii(np.zeros((H, W, 3), np.uint8))
    with pytest.raises(ValueError):
        hue_hist(np.zeros((H, W), np.uint8))
    with pytest.raises(ValueError):
        integral_invariant(np.zeros((H, W), np.uint8), q=0)


@settings(max_examples=25, deadline=None)
@given(st.integers(4, 40), st.integers(4, 40), st.integers(0, 2**32 - 1))
def test_every_feature_is_a_distribution_or_empty(h, w, seed):
    rng = np.random.default_rng(seed)
    levels = rng.integers(1, 256)
    colour = (rng.integers(0, levels, (h, w, 3))).astype(np.uint8)
    frame = prepare(colour, (w, h))
    for name, f in extract_many(FEATURE_NAMES, frame).items():
        assert f.shape == (GLOBAL_FEATURES[name].dim,)
        assert np.isfinite(f).all() and f.min() >= 0
        assert f.sum() == pytest.approx(1.0, abs=1e-5) or not f.any()
