"""Tie-point pairs matched in batches, apart from the packing: the same pairs, the same tie
points, and the same geometry as when one process matches them all."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from tests.core.geometry.scene import survey
from vloc.workers.core import tiepairs
from vloc.workers.core.geo import GeoOrigin
from vloc.workers.core.geometry import build_geometry, match_pair, tie_pairs, tie_reach
from vloc.workers.core.geometry.pairs import keep_some, match_pairs
from vloc.workers.core.mapbuild import local_frame, save_tie_points
from vloc.workers.core.sift import SiftFeatures

ORIGIN = GeoOrigin(42.0, -76.5, 300.0)


@pytest.fixture(scope="module")
def surveyed():
    s = survey(np.random.default_rng(5), rows=2, cols=4, max_tilt_deg=3.0)
    lat, lon = ORIGIN.to_wgs84(s.positions[:, 0], s.positions[:, 1])
    _, xy, _ = local_frame(lat, lon, list(s.altitudes))
    return s, lat, lon, xy


def _write_ties(s, folder):
    stems = {}
    for i, (kp, desc) in enumerate(zip(s.keypoints, s.image_descriptors, strict=True)):
        stems[i] = str(folder / f"img{i}")
        save_tie_points(SiftFeatures(np.asarray(kp, np.float32),
                                     np.asarray(desc, np.uint8)), stems[i])
    return stems


def test_the_plan_is_the_pairs_the_geometry_matches(surveyed):
    s, lat, lon, xy = surveyed
    planned = tiepairs.plan(lat, lon, list(s.altitudes))
    assert planned == tie_pairs(xy)
    assert planned == sorted(set(planned)) and all(a < b for a, b in planned)
    # every image within reach of another is in some pair
    assert {i for p in planned for i in p} == set(range(len(xy)))


def test_a_pair_matches_the_same_whoever_matches_it_and_whatever_came_before(surveyed):
    s, *_ = surveyed
    kp, desc = s.keypoints, s.image_descriptors
    first = match_pair(0, 1, kp[0], desc[0], kp[1], desc[1])
    # other pairs matched in between, OpenCV's generator and NumPy's moved on
    match_pair(1, 2, kp[1], desc[1], kp[2], desc[2])
    cv2.setRNGSeed(99)
    np.random.default_rng().random(10)
    again = match_pair(0, 1, kp[0], desc[0], kp[1], desc[1])
    assert first is not None and len(first.pa) > 30     # every inlier: the draw comes later
    np.testing.assert_array_equal(first.pa, again.pa)
    np.testing.assert_array_equal(first.homography, again.homography)
    # indices of a 50,000-image map seed OpenCV too (its seed is a 32-bit integer)
    assert match_pair(49_998, 49_999, kp[0], desc[0], kp[1], desc[1]) is not None


def test_each_pair_keeps_a_few_tie_points_drawn_in_the_pairs_order(surveyed):
    s, *_ = surveyed
    kp, desc = s.keypoints, s.image_descriptors
    pairs = [match_pair(a, b, kp[a], desc[a], kp[b], desc[b]) for a, b in ((0, 1), (1, 2))]
    few = pairs[0].__class__(0, 2, pairs[0].pa[:12], pairs[0].pb[:12], pairs[0].homography)
    kept = keep_some([pairs[0], few, pairs[1]], np.random.default_rng(0), 30)
    assert [len(p.pa) for p in kept] == [30, 12, 30]
    np.testing.assert_array_equal(kept[1].pa, few.pa)        # fewer than 30: all kept
    # the slow obvious reference: one generator, a draw for each pair that has more
    rng = np.random.default_rng(0)
    for full, got in ((pairs[0], kept[0]), (pairs[1], kept[2])):
        rows = np.sort(rng.choice(len(full.pa), size=30, replace=False))
        np.testing.assert_array_equal(got.pa, full.pa[rows])
        np.testing.assert_array_equal(got.pb, full.pb[rows])


def test_batches_give_the_pairs_and_the_geometry_of_one_process(surveyed, tmp_path):
    s, lat, lon, xy = surveyed
    stems = _write_ties(s, tmp_path)
    planned = tiepairs.plan(lat, lon, list(s.altitudes))
    ids = [100 + i for i in range(len(xy))]
    tiepairs.save_plan(tmp_path, ids)
    verified = 0
    for k in range(0, len(planned), 3):           # batches of three, as workers would
        batch = planned[k:k + 3]
        verified += tiepairs.match_batch({i: stems[i] for p in batch for i in p}, batch,
                                         tmp_path / f"pairs-{k:06d}.npz")
    known = tiepairs.load_results(tmp_path, ids)
    assert set(known) == set(planned)
    assert verified == sum(p is not None for p in known.values()) >= len(xy)
    serial = match_pairs(s.keypoints, s.image_descriptors, xy, max_distance=tie_reach(xy))
    assert [(p.a, p.b) for p in serial] == sorted(k for k, p in known.items() if p is not None)
    apart = keep_some([p for _, p in sorted(known.items()) if p is not None],
                      np.random.default_rng(0))
    for p, q in zip(serial, apart, strict=True):
        np.testing.assert_array_equal(p.pa, q.pa)
        np.testing.assert_array_equal(p.pb, q.pb)
        np.testing.assert_array_equal(p.homography, q.homography)
    # the geometry built from the batches' pairs is the one built by matching them here
    alt = np.asarray(s.altitudes)
    here = build_geometry(s.keypoints, s.image_descriptors, xy, alt, s.K)
    apart = build_geometry(s.keypoints, s.image_descriptors, xy, alt, s.K, known_pairs=known)
    assert here is not None and apart is not None
    np.testing.assert_array_equal(here.centres, apart.centres)
    np.testing.assert_array_equal(here.rotations, apart.rotations)


def test_pairs_with_missing_tie_points_are_left_to_the_packing(surveyed, tmp_path):
    s, lat, lon, xy = surveyed
    stems = _write_ties(s, tmp_path)
    (tmp_path / "img2.kp.npy").unlink()
    planned = tiepairs.plan(lat, lon, list(s.altitudes))
    tiepairs.save_plan(tmp_path, list(range(len(xy))))
    tiepairs.match_batch(stems, planned, tmp_path / "pairs-000000.npz")
    known = tiepairs.load_results(tmp_path, list(range(len(xy))))
    assert set(known) == {p for p in planned if 2 not in p}


def test_results_for_other_images_are_ignored(surveyed, tmp_path):
    s, lat, lon, xy = surveyed
    stems = _write_ties(s, tmp_path)
    planned = tiepairs.plan(lat, lon, list(s.altitudes))
    ids = list(range(len(xy)))
    tiepairs.match_batch(stems, planned, tmp_path / "pairs-000000.npz")
    assert tiepairs.load_results(tmp_path, ids) == {}          # no plan recorded
    tiepairs.save_plan(tmp_path, ids)
    assert len(tiepairs.load_results(tmp_path, ids)) == len(planned)
    # an image deleted after planning: indices would name other images
    assert tiepairs.load_results(tmp_path, ids[:-1]) == {}
    assert tiepairs.load_results(tmp_path / "nothing-here", ids) == {}


def test_an_empty_batch_round_trips(tmp_path):
    tiepairs.save_results([(0, 1, None)], tmp_path / "pairs-000000.npz")
    tiepairs.save_plan(tmp_path, [7, 8])
    assert tiepairs.load_results(tmp_path, [7, 8]) == {(0, 1): None}
    # written under a hidden name first: a file cut short by a dying worker is never read
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pairs-000000.npz",
                                                           tiepairs.PLAN_FILE]
    (tmp_path / ".pairs-000001.npz").write_bytes(b"cut short")
    assert tiepairs.load_results(tmp_path, [7, 8]) == {(0, 1): None}
