"""Similarity of a frame with map images (localisers/scoring.py) against direct formulas."""

from __future__ import annotations

import numpy as np
import pytest

from vloc.workers.core.geo import GeoOrigin
from vloc.workers.core.image import prepare
from vloc.workers.core.localisers.scoring import global_similarity, sift_similarity
from vloc.workers.core.mapbuild import assemble_map, extract_image_features
from vloc.workers.core.measures import weiss_similarity
from vloc.workers.core.query import QueryFrame
from vloc.workers.core.sift import ratio_matches


@pytest.fixture(scope="module")
def three_images():
    rng = np.random.default_rng(3)
    images = []
    for _ in range(3):
        small = rng.integers(0, 256, (30, 40, 3), dtype=np.uint8)
        images.append(prepare(np.repeat(np.repeat(small, 8, axis=0), 8, axis=1)))
    origin = GeoOrigin(48.5, 9.0, 0.0)
    lat, lon = origin.to_wgs84(np.array([0.0, 10.0, 20.0]), np.zeros(3))
    the_map = assemble_map(names=["a", "b", "c"], lats=lat, lons=lon, alts=[0.0] * 3,
                           features=[extract_image_features(f) for f in images], origin=origin)
    return images, the_map


def test_global_similarity_is_weiss_product_for_wgoh_and_wgii(three_images):
    images, the_map = three_images
    q, _ = QueryFrame(images[1]).global_features(("wgoh", "wgii"))
    idx = np.array([2, 0, 1])
    got = global_similarity(q, the_map, idx, features=("wgoh", "wgii"), measure="weiss")
    g = the_map.global_features
    want = weiss_similarity(q["wgoh"], g["wgoh"][idx], q["wgii"], g["wgii"][idx])
    np.testing.assert_allclose(got, want, rtol=1e-12)
    assert got[2] == pytest.approx(1.0)  # the image itself


def test_sift_similarity_is_the_share_of_matched_keypoints(three_images):
    images, the_map = three_images
    q, _ = QueryFrame(images[0]).sift()
    got = sift_similarity(q, the_map, np.array([0, 1, 2]), ratio=0.8, verify="none")
    for j in range(3):
        want = len(ratio_matches(q.descriptors, the_map.sift(j).descriptors, ratio=0.8)) / len(q)
        assert got[j] == want
    assert got[0] == 1.0 and got[1] < 0.2
    verified = sift_similarity(q, the_map, np.array([0]), ratio=0.8, verify="homography")
    assert verified[0] == 1.0  # every match of an image with itself is a homography inlier
