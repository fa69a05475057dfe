"""Heading normalisation: exact quarter and half turns, direction, errors."""

from __future__ import annotations

import numpy as np
import pytest

from vloc.workers.core.features import north_up


@pytest.fixture(scope="module")
def square() -> np.ndarray:
    return np.random.default_rng(0).integers(0, 256, (40, 40, 3), dtype=np.uint8)


def test_north_up_heading_zero_is_the_image(square):
    out = north_up(square, 0.0)
    np.testing.assert_array_equal(out, square)
    assert out is not square
    np.testing.assert_array_equal(north_up(square, 360.0), square)


def test_facing_east_turns_the_image_clockwise(square):
    # up points east, so north is on the left: the left edge must come to the top
    np.testing.assert_array_equal(north_up(square, 90.0), np.rot90(square, -1))
    np.testing.assert_array_equal(north_up(square, 270.0), np.rot90(square, 1))
    np.testing.assert_array_equal(north_up(square, -90.0), np.rot90(square, 1))


def test_half_turn_is_exact_on_any_shape():
    grey = np.random.default_rng(1).integers(0, 256, (30, 52), dtype=np.uint8)
    np.testing.assert_array_equal(north_up(grey, 180.0), grey[::-1, ::-1])


def test_north_up_then_back_restores_the_centre():
    grey = np.random.default_rng(2).integers(0, 256, (60, 60), dtype=np.uint8)
    back = north_up(north_up(grey, 90.0), -90.0)
    np.testing.assert_array_equal(back, grey)


def test_bad_inputs():
    with pytest.raises(ValueError, match="finite"):
        north_up(np.zeros((4, 4), np.uint8), float("nan"))
    with pytest.raises(ValueError, match="uint8"):
        north_up(np.zeros((4, 4), np.float32), 10.0)
