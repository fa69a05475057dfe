"""Tie points between two map images: thin pairs that overlap verify, thin pairs that do
not are refused, on exact synthetic views (:mod:`tests.core.geometry.scene`)."""

from __future__ import annotations

import numpy as np
import pytest

from tests.core.geometry.scene import HEIGHT, WIDTH, survey
from vloc.workers.core.geometry import pairs
from vloc.workers.core.geometry.pairs import match_pair, ransac_floor


def _thin_pair(seed: int, common: int, outliers: int):
    """Two overlapping survey images reduced to ``common`` shared points, plus ``outliers``
    keypoints per image whose descriptors match across the pair at unrelated pixels: what
    a thin pair looks like after the ratio test."""
    rng = np.random.default_rng(seed)
    s = survey(rng, rows=1, cols=2, spacing=15.0, relief=True)
    _, ia, ib = np.intersect1d(s.point_ids[0], s.point_ids[1], return_indices=True)
    keep = rng.choice(len(ia), common, replace=False)
    ia, ib = ia[keep], ib[keep]
    fake = rng.integers(0, 256, size=(outliers, 128), dtype=np.uint8)

    def image(i, rows):
        kp = np.zeros((common + outliers, 4), np.float32)
        kp[:common] = s.keypoints[i][rows]
        kp[common:, 0] = rng.uniform(0, WIDTH - 1, outliers)
        kp[common:, 1] = rng.uniform(0, HEIGHT - 1, outliers)
        return kp, np.concatenate([s.image_descriptors[i][rows], fake])

    (kpa, da), (kpb, db) = image(0, ia), image(1, ib)
    return kpa, da, kpb, db


@pytest.mark.parametrize("seed", range(4))
def test_a_thin_pair_that_overlaps_verifies_on_its_true_matches(seed):
    # 24 ratio matches of which 17 are true: just over the 15 inliers a pair needs
    kpa, da, kpb, db = _thin_pair(seed, common=17, outliers=7)
    found = match_pair(0, 1, kpa, da, kpb, db, min_inliers=15, seed=seed)
    assert found is not None
    true = found.matches[:, 0] < 17
    assert true.sum() >= 15
    assert np.array_equal(found.matches[true, 0], found.matches[true, 1])
    assert (~true).sum() <= 1


@pytest.mark.parametrize("seed", range(4))
def test_a_thin_pair_of_chance_matches_is_refused(seed):
    # 28 matches at unrelated pixels: no two-view geometry holds 15 of them
    kpa, da, kpb, db = _thin_pair(seed, common=0, outliers=28)
    assert match_pair(0, 1, kpa, da, kpb, db, min_inliers=15, seed=seed) is None


def test_too_few_ratio_matches_are_refused_before_any_geometry():
    kpa, da, kpb, db = _thin_pair(0, common=14, outliers=0)
    assert match_pair(0, 1, kpa, da, kpb, db, min_inliers=15) is None


def test_the_ransac_floor_is_the_least_inlier_ratio_a_pair_could_verify_with():
    assert ransac_floor(28, 15) == pytest.approx(15 / 28)
    assert ransac_floor(15, 15) == 1.0
    assert ransac_floor(60, 15) == 0.25 and ransac_floor(400, 15) == 0.25   # COLMAP's own
    assert ransac_floor(10, 15) == 1.0 and ransac_floor(0, 15) == 1.0


@pytest.mark.parametrize("matches", [20, 25, 30, 40])
@pytest.mark.parametrize("seed", range(6))
def test_a_pair_at_the_floor_verifies_as_it_does_without_the_cap(monkeypatch, matches, seed):
    # just the 15 true matches a pair needs among ``matches``: the inlier ratio the cap
    # assumes. Capped, the RANSAC finds as many of them as without the cap (without it,
    # more trials may take in another chance match that fits the epipolar lines too).
    kpa, da, kpb, db = _thin_pair(seed, common=15, outliers=matches - 15)
    capped = match_pair(0, 1, kpa, da, kpb, db, min_inliers=15, seed=seed)
    monkeypatch.setattr(pairs, "ransac_floor", lambda n, k: 0.25)        # COLMAP's default
    uncapped = match_pair(0, 1, kpa, da, kpb, db, min_inliers=15, seed=seed)
    assert capped is not None and uncapped is not None
    true = capped.matches[:, 0] < 15
    assert true.sum() >= 13
    assert np.array_equal(capped.matches[true, 0], capped.matches[true, 1])
    assert true.sum() == (uncapped.matches[:, 0] < 15).sum()
