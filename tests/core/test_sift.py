"""SIFT matching against a slow reference, and the feature reductions."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vloc.workers.core.sift import (
    SiftFeatures,
    extract_sift,
    match_share,
    ratio_matches,
    reduce_map,
    reduce_with_previous,
    reduction_masks,
)


def _texture(seed: int, shape=(240, 320)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = cv2.resize(rng.integers(0, 256, (shape[0] // 8, shape[1] // 8), dtype=np.uint8),
                     (shape[1], shape[0]), interpolation=cv2.INTER_CUBIC)
    for _ in range(40):
        c = tuple(int(v) for v in rng.integers(0, [shape[1], shape[0]]))
        cv2.circle(img, c, int(rng.integers(3, 20)), int(rng.integers(0, 256)), -1)
    return img


def _slow_ratio_matches(a, b, ratio):
    out = []
    for i, d in enumerate(a.astype(np.float64)):
        dist = np.sqrt(((b.astype(np.float64) - d) ** 2).sum(axis=1))
        order = np.argsort(dist)
        if dist[order[0]] < ratio * dist[order[1]]:
            out.append((i, order[0]))
    return np.array(out, dtype=np.int64).reshape(-1, 2)


def test_ratio_matches_equal_the_loop_reference():
    rng = np.random.default_rng(0)
    a = rng.integers(0, 60, (80, 128)).astype(np.uint8)
    b = np.concatenate([a[:30] + rng.integers(0, 3, (30, 128)).astype(np.uint8),
                        rng.integers(0, 60, (50, 128)).astype(np.uint8)])
    fast = ratio_matches(a, b, ratio=0.8)
    slow = _slow_ratio_matches(a, b, 0.8)
    np.testing.assert_array_equal(fast, slow)
    assert len(fast) >= 25  # the 30 near-copies are found


def test_ratio_matches_hand_case():
    a = np.array([[0, 0], [10, 10]], dtype=np.float32)
    b = np.array([[0, 1], [0, 9], [10, 10.5]], dtype=np.float32)
    # row 0: distances 1, 9, ... -> ratio 1/9 passes; row 1: 0.5 vs 10.0 -> passes
    np.testing.assert_array_equal(ratio_matches(a, b), [[0, 0], [1, 2]])
    # an ambiguous query (equidistant to two) fails the ratio test
    amb = np.array([[0, 5]], dtype=np.float32)
    assert len(ratio_matches(amb, np.array([[0, 0], [0, 10]], dtype=np.float32))) == 0


def test_match_share_same_image_high_other_image_low():
    img = _texture(1)
    same = extract_sift(img)
    shifted = extract_sift(np.roll(img, 7, axis=1))
    other = extract_sift(_texture(2))
    assert len(same) > 50
    assert match_share(same, shifted) > 0.5
    assert match_share(same, other) < 0.1
    assert match_share(SiftFeatures.empty(), same) == 0.0


def test_map_reduction_keeps_what_neighbours_share():
    base = _texture(3)
    feats = [extract_sift(np.roll(base, 5 * k, axis=1)) for k in range(3)]
    feats.append(extract_sift(_texture(4)))  # far away and unrelated
    pos = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [50.0, 0.0]])
    masks = reduction_masks(feats, pos)
    reduced = reduce_map(feats, pos)
    for f, m, r in zip(feats, masks, reduced, strict=True):
        assert len(r) == m.sum() <= len(f)
    assert masks[1].mean() > 0.5  # overlapping neighbours keep most keypoints
    assert masks[3].mean() < 0.2  # an image matching nothing keeps little


def test_query_reduction_falls_back_to_whole_frame_without_overlap():
    a = extract_sift(_texture(5))
    b = extract_sift(_texture(6))
    assert reduce_with_previous(a, None) is a
    assert len(reduce_with_previous(a, b, min_keep=20)) == len(a)
    near = extract_sift(np.roll(_texture(5), 4, axis=0))
    assert 0 < len(reduce_with_previous(a, near)) < len(a) + 1


@pytest.mark.parametrize("n", [0, 1])
def test_tiny_inputs_give_no_matches(n):
    a = np.zeros((n, 128), np.uint8)
    assert ratio_matches(a, np.zeros((1, 128), np.uint8)).shape == (0, 2)


def test_a_tie_for_nearest_is_no_match():
    a = np.array([[0.0, 0.0]], np.float32)
    b = np.array([[3.0, 0.0], [0.0, 3.0], [9.0, 9.0]], np.float32)
    assert len(ratio_matches(a, b, ratio=0.99)) == 0
    assert len(ratio_matches(a, b[1:], ratio=0.99)) == 1
