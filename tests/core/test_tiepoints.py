"""A map image's tie points: extracted at working-resolution pixels, written to disk and
read back memory-mapped."""

from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial import cKDTree

from vloc.workers.core.image import prepare
from vloc.workers.core.sift import SiftFeatures, extract_sift
from vloc.workers.core.tiepoints import (
    TIE_KEYPOINTS,
    extract_tie_points,
    load_tie_points,
    save_tie_points,
)


def test_tie_points_are_in_working_resolution_pixels():
    rng = np.random.default_rng(7)
    # blobs of texture on a 640x480 image: SIFT finds them at both resolutions
    image = cv2.GaussianBlur(rng.integers(0, 256, (480, 640, 3), dtype=np.uint8), (0, 0), 2.0)
    ok, png = cv2.imencode(".png", image)
    ties = extract_tie_points(png.tobytes())
    assert 300 < len(ties) <= TIE_KEYPOINTS
    work = extract_sift(prepare(image).grey)
    # each working-resolution keypoint has a tie point at the same place (a wrong scale or
    # offset moves them by tens of pixels at the far edges)
    tree = cKDTree(ties.keypoints[:, :2])
    d, _ = tree.query(work.keypoints[:, :2])
    assert np.median(d) < 0.5
    assert ties.keypoints[:, 0].max() < 320 and ties.keypoints[:, 1].max() < 240


def test_tie_points_saved_and_read_back_memory_mapped(tmp_path):
    rng = np.random.default_rng(5)
    for n in (7, 0):
        tie = SiftFeatures(rng.random((n, 4), dtype=np.float32) * 300,
                           rng.integers(0, 256, (n, 128), dtype=np.uint8))
        save_tie_points(tie, tmp_path / f"img{n}")
        back = load_tie_points(tmp_path / f"img{n}")
        np.testing.assert_array_equal(back.keypoints, tie.keypoints)
        np.testing.assert_array_equal(back.descriptors, tie.descriptors)
        # read through the page cache, not held in the worker's memory
        assert isinstance(back.descriptors, np.memmap)
    assert load_tie_points(tmp_path / "never-written") is None
