"""ORB and RootSIFT local features: known answers, loop references, rotation invariance."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vloc.workers.core.features.orb import (
    MAX_KEYPOINTS,
    extract_orb,
    hamming_ratio_matches,
    unpack_bits,
)
from vloc.workers.core.features.rootsift import rootsift


@pytest.fixture(scope="module")
def texture() -> np.ndarray:
    """A 240x240 grey image of blobs and boxes: plenty of corners at every orientation."""
    rng = np.random.default_rng(3)
    img = cv2.resize(rng.integers(0, 256, (40, 40), dtype=np.uint8), (240, 240),
                     interpolation=cv2.INTER_CUBIC)
    for _ in range(150):
        c = (int(rng.integers(0, 240)), int(rng.integers(0, 240)))
        v = int(rng.integers(0, 256))
        if rng.random() < 0.5:
            cv2.circle(img, c, int(rng.integers(3, 12)), v, -1)
        else:
            cv2.rectangle(img, c, (c[0] + int(rng.integers(4, 20)), c[1] + int(rng.integers(4, 20))),
                          v, -1)
    return img


def test_unpack_bits_known_answer_and_hamming_equals_squared_distance():
    d = np.array([[0b10000001, 0xFF], [0, 0b01000000]], dtype=np.uint8)
    bits = unpack_bits(d)
    assert bits.dtype == np.float32 and bits.shape == (2, 16)
    np.testing.assert_array_equal(bits[0], [1, 0, 0, 0, 0, 0, 0, 1] + [1] * 8)
    np.testing.assert_array_equal(bits[1], [0] * 9 + [1] + [0] * 6)
    rng = np.random.default_rng(0)
    a, b = rng.integers(0, 256, (2, 5, 32), dtype=np.uint8)
    popcount = [[sum(bin(int(x) ^ int(y)).count("1") for x, y in zip(ra, rb, strict=True))
                 for rb in b] for ra in a]
    ua, ub = unpack_bits(a), unpack_bits(b)
    sq = ((ua[:, None, :] - ub[None, :, :]) ** 2).sum(axis=2)
    np.testing.assert_array_equal(sq, popcount)


def test_orb_on_a_textured_image(texture):
    orb = extract_orb(texture)
    assert 100 <= len(orb) <= MAX_KEYPOINTS
    assert orb.descriptors.shape == (len(orb), 32) and orb.descriptors.dtype == np.uint8
    assert orb.keypoints.shape == (len(orb), 4) and orb.keypoints.dtype == np.float32
    assert len(extract_orb(texture, n_features=50)) <= 50


def test_orb_of_a_flat_image_is_empty():
    orb = extract_orb(np.full((240, 320), 90, np.uint8))
    assert len(orb) == 0 and orb.descriptors.shape == (0, 32)
    with pytest.raises(ValueError, match="uint8"):
        extract_orb(np.zeros((10, 10), np.float32))


def test_orb_descriptors_survive_a_quarter_turn(texture):
    """Steered BRIEF: the same corners found in the turned image carry nearly the same bits."""
    a = extract_orb(texture)
    b = extract_orb(np.ascontiguousarray(np.rot90(texture)))
    # np.rot90 turns counter-clockwise: (x, y) -> (y, W - 1 - x)
    moved = np.stack([a.keypoints[:, 1], 239 - a.keypoints[:, 0]], axis=1)
    d_px = np.linalg.norm(moved[:, None] - b.keypoints[None, :, :2], axis=2)
    pairs = [(i, int(j)) for i, j in enumerate(d_px.argmin(axis=1)) if d_px[i, j] < 1.0]
    assert len(pairs) >= 50
    hamming = np.array([((unpack_bits(a.descriptors[[i]]) - unpack_bits(b.descriptors[[j]])) ** 2)
                        .sum() for i, j in pairs])
    # unrelated ORB descriptors differ in about 128 of 256 bits
    assert np.median(hamming) < 40


def test_rootsift_known_answers():
    d = np.zeros((3, 128), np.uint8)
    d[0, 0] = 4
    d[1, :3] = (1, 1, 2)
    r = rootsift(d)
    assert r.dtype == np.float32 and r.shape == (3, 128)
    np.testing.assert_allclose(r[0, :2], [1.0, 0.0])
    np.testing.assert_allclose(r[1, :4], [0.5, 0.5, np.sqrt(0.5), 0.0], rtol=1e-6)
    np.testing.assert_array_equal(r[2], 0.0)  # no gradients, no direction


def test_rootsift_equals_a_loop_and_hellinger():
    rng = np.random.default_rng(1)
    d = rng.integers(0, 256, (6, 128)).astype(np.uint8)
    r = rootsift(d)
    for row, out in zip(d, r, strict=True):
        total = sum(int(v) for v in row)
        np.testing.assert_allclose(out, [np.sqrt(int(v) / total) for v in row], rtol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(r, axis=1), 1.0, rtol=1e-6)
    # Euclidean distance of RootSIFT vectors is the Hellinger distance of the L1 histograms
    p, q = d[0] / d[0].sum(), d[1] / d[1].sum()
    hellinger_sq = ((np.sqrt(p) - np.sqrt(q)) ** 2).sum()
    assert ((r[0] - r[1]) ** 2).sum() == pytest.approx(hellinger_sq, rel=1e-5)
    with pytest.raises(ValueError, match="128"):
        rootsift(np.zeros((2, 64)))


def _hamming_ratio_loop(a: np.ndarray, b: np.ndarray, ratio: float) -> list[tuple[int, int]]:
    """The slow obvious reference: every distance by counting differing bits."""
    out = []
    for i, da in enumerate(a):
        d = [sum(bin(int(x) ^ int(y)).count("1") for x, y in zip(da, db, strict=True))
             for db in b]
        order = sorted(range(len(b)), key=lambda j: (d[j], j))
        if d[order[0]] < ratio * d[order[1]]:
            out.append((i, order[0]))
    return out


def test_hamming_ratio_matches_equal_a_loop():
    rng = np.random.default_rng(5)
    b = rng.integers(0, 256, (60, 32), dtype=np.uint8)
    # half the queries are noisy copies of rows of b, half unrelated
    a = rng.integers(0, 256, (40, 32), dtype=np.uint8)
    a[:20] = b[:20] ^ (rng.random((20, 32)) < 0.02).astype(np.uint8)
    got = hamming_ratio_matches(a, b, ratio=0.8)
    want = _hamming_ratio_loop(a, b, 0.8)
    # a tie for nearest is resolved by either side alike only when the distances differ
    assert sorted(map(tuple, got.tolist())) == sorted(want)
    assert {(i, i) for i in range(20)} <= set(map(tuple, got.tolist()))
    assert got.shape[1] == 2 and got.dtype == np.int64


def test_hamming_ratio_matches_need_two_candidates():
    a = np.zeros((3, 32), np.uint8)
    assert hamming_ratio_matches(a, a[:1]).shape == (0, 2)
    assert hamming_ratio_matches(a[:0], a).shape == (0, 2)


def test_hamming_ratio_matches_are_the_brute_force_matchers():
    """The same neighbours as OpenCV's brute-force matcher, ties and their order included:
    maps built before the matcher changed localise as they did."""
    rng = np.random.default_rng(11)
    b = rng.integers(0, 256, (300, 32), dtype=np.uint8)
    # coarse descriptors (four bytes vary) make equal distances common
    a = np.repeat(b[:1], 200, axis=0)
    a[:, :4] = rng.integers(0, 256, (200, 4), dtype=np.uint8)
    b[:150, 4:] = b[0, 4:]
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
    for ratio in (0.7, 0.83, 1.0):
        want = [(m.queryIdx, m.trainIdx) for m, n in matcher.knnMatch(a, b, k=2)
                if m.distance < ratio * n.distance]
        got = hamming_ratio_matches(a, b, ratio=ratio)
        assert got.tolist() == [list(p) for p in want]
        assert 0 < len(want) < len(a)
