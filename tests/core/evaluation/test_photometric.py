"""Photometric variants: determinism from a seed, direction of change, dtype and shape."""

from __future__ import annotations

import numpy as np
import pytest

from vloc.workers.core.evaluation.photometric import VARIANTS, apply_variant, variant_rng

RANDOM_VARIANTS = tuple(v for v in VARIANTS if v != "none")


@pytest.fixture(scope="module")
def image() -> np.ndarray:
    """A textured colour image of odd size (37x53): smooth gradients plus noise."""
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:37, 0:53]
    base = np.stack([60 + 2 * xx, 80 + 3 * yy, 150 - xx - yy], axis=-1).astype(np.float64)
    noisy = base + rng.normal(0, 20, base.shape)
    return np.clip(noisy, 10, 245).astype(np.uint8)


def _ratio(img: np.ndarray, num: int, den: int) -> float:
    return float(img[..., num].astype(np.float64).mean() / img[..., den].astype(np.float64).mean())


def test_variants_listed():
    assert VARIANTS[0] == "none"
    assert {"darker", "brighter", "dusk", "warm", "shadows"} <= set(VARIANTS)


@pytest.mark.parametrize("name", VARIANTS)
def test_keeps_dtype_shape_and_input(image, name):
    before = image.copy()
    out = apply_variant(image, name, rng=variant_rng(3, 0))
    assert out.dtype == np.uint8 and out.shape == image.shape
    assert out is not image
    np.testing.assert_array_equal(image, before)


@pytest.mark.parametrize("name", RANDOM_VARIANTS)
def test_deterministic_for_a_seed_and_different_for_another(image, name):
    a = apply_variant(image, name, rng=variant_rng(11, 4))
    b = apply_variant(image, name, rng=variant_rng(11, 4))
    np.testing.assert_array_equal(a, b)
    others = [apply_variant(image, name, rng=variant_rng(s, 4)) for s in (12, 13)]
    assert any(not np.array_equal(a, o) for o in others)
    # Another frame index of the same seed is another draw too.
    assert not np.array_equal(a, apply_variant(image, name, rng=variant_rng(11, 5)))


def test_none_is_identity(image):
    np.testing.assert_array_equal(apply_variant(image, "none", rng=variant_rng(0, 0)), image)


def test_variant_rng_is_the_spawned_child_and_order_free():
    # Reference: child i of SeedSequence(seed).spawn(), built the obvious way.
    children = np.random.SeedSequence(42).spawn(6)
    for i in (5, 0, 3):
        expected = np.random.default_rng(children[i]).random(5)
        np.testing.assert_array_equal(variant_rng(42, i).random(5), expected)
    assert not np.array_equal(variant_rng(42, 1).random(5), variant_rng(43, 1).random(5))
    with pytest.raises(ValueError, match="non-negative"):
        variant_rng(-1, 0)


@pytest.mark.parametrize("seed", range(5))
def test_darker_and_brighter_move_every_pixel_one_way(image, seed):
    dark = apply_variant(image, "darker", rng=variant_rng(seed, 0))
    bright = apply_variant(image, "brighter", rng=variant_rng(seed, 0))
    assert np.all(dark <= image) and dark.mean() < 0.7 * image.mean()
    assert np.all(bright >= image) and bright.mean() > 1.1 * image.mean()


def test_darker_is_a_monotone_tone_curve():
    ramp = np.repeat(np.arange(256, dtype=np.uint8)[None, :, None], 3, axis=2)
    out = apply_variant(ramp, "darker", rng=variant_rng(0, 0))[0, :, 0].astype(int)
    assert out[0] == 0 and np.all(np.diff(out) >= 0)
    assert 0.45 * 255 - 1 <= out[255] <= 0.65 * 255 + 1
    # every channel gets the same curve: grey stays grey
    assert np.all(apply_variant(ramp, "darker", rng=variant_rng(0, 0)).std(axis=2) == 0)


@pytest.mark.parametrize("seed", range(5))
def test_dusk_is_darker_flatter_and_bluer(image, seed):
    out = apply_variant(image, "dusk", rng=variant_rng(seed, 0))
    assert out.mean() < 0.7 * image.mean()
    assert out.astype(np.float64).std() < 0.6 * image.astype(np.float64).std()
    assert _ratio(out, 0, 2) > 1.05 * _ratio(image, 0, 2)  # blue / red


@pytest.mark.parametrize("seed", range(5))
def test_warm_raises_red_over_blue(image, seed):
    out = apply_variant(image, "warm", rng=variant_rng(seed, 0))
    assert _ratio(out, 2, 0) > 1.15 * _ratio(image, 2, 0)  # red / blue
    assert np.all(out[..., 0] <= image[..., 0]) and np.all(out[..., 2] >= image[..., 2])


def test_shadows_darken_regions_with_smooth_edges():
    flat = np.full((240, 320, 3), 200, dtype=np.uint8)
    shaded_share = []
    for seed in range(8):
        out = apply_variant(flat, "shadows", rng=variant_rng(seed, 0)).astype(int)
        assert np.all(out <= 200)
        green = out[..., 1]
        shaded_share.append(float(np.mean(green < 180)))
        # A hard edge would jump by 80-130 grey levels between neighbours; the penumbra
        # (Gaussian, sigma >= 3.2 px) limits the step to about 0.125 of the depth.
        steepest = max(np.abs(np.diff(green, axis=0)).max(), np.abs(np.diff(green, axis=1)).max())
        assert steepest < 30
        # the deepest shade keeps 35-60 % of the light, a bit more in blue than in red
        darkest = np.unravel_index(np.argmin(green), green.shape)
        if green[darkest] < 150:
            b, g, r = out[darkest]
            assert b >= g >= r
    assert max(shaded_share) > 0.02, "no seed cast a visible shadow"
    assert min(shaded_share) < max(shaded_share), "shadow placement ignores the seed"


def test_rejects_unknown_names_and_bad_images(image):
    with pytest.raises(ValueError, match="unknown photometric variant 'night'.*darker"):
        apply_variant(image, "night", rng=variant_rng(0, 0))
    with pytest.raises(ValueError, match="uint8"):
        apply_variant(image.astype(np.float32), "darker", rng=variant_rng(0, 0))
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        apply_variant(image[..., 0], "darker", rng=variant_rng(0, 0))
