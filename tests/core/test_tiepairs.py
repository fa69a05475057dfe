"""Tie-point pairs matched in batches, apart from the packing: the same pairs, the same tie
points, and the same geometry as when one process matches them all."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from tests.core.geometry.scene import survey
from vloc.workers.core import tiepairs
from vloc.workers.core.geo import GeoOrigin, local_frame
from vloc.workers.core.geometry import (
    REACH_GROWTH,
    KeptModels,
    build_geometry,
    match_pair,
    tie_pairs,
    tie_reach,
)
from vloc.workers.core.geometry.pairs import PairMatches, match_pairs
from vloc.workers.core.sift import SiftFeatures
from vloc.workers.core.tiepoints import save_tie_points

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
    assert first is not None and (first.a, first.b) == (0, 1)
    np.testing.assert_array_equal(first.matches, again.matches)
    assert first.config == again.config
    # the verified matches are keypoint indices, and exactly the points both images see
    _, ia, ib = np.intersect1d(s.point_ids[0], s.point_ids[1], return_indices=True)
    assert first.matches.dtype == np.int64
    assert sorted(map(tuple, first.matches.tolist())) == sorted(zip(ia.tolist(), ib.tolist(), strict=True))
    # indices of a 50,000-image map seed COLMAP too (its seed is a 31-bit integer)
    far = match_pair(49_998, 49_999, kp[0], desc[0], kp[1], desc[1])
    assert far is not None and len(far) == len(first)


def test_batches_give_the_pairs_and_the_geometry_of_one_process(surveyed, tmp_path):
    s, lat, lon, xy = surveyed
    stems = _write_ties(s, tmp_path)
    planned = tiepairs.plan(lat, lon, list(s.altitudes))
    ids = [100 + i for i in range(len(xy))]
    verified = 0
    for k in range(0, len(planned), 3):           # batches of three, as workers would
        batch = planned[k:k + 3]
        verified += tiepairs.match_batch({i: stems[i] for p in batch for i in p}, batch,
                                         tmp_path / f"pairs-{k:06d}.npz", image_ids=ids)
    known = tiepairs.load_results(tmp_path, ids)
    assert set(known) == set(planned)
    assert verified == sum(p is not None for p in known.values()) >= len(xy)
    serial = match_pairs(s.keypoints, s.image_descriptors, tie_pairs(xy))
    apart = [p for _, p in sorted(known.items()) if p is not None]
    assert [(p.a, p.b) for p in serial] == [(p.a, p.b) for p in apart]
    for p, q in zip(serial, apart, strict=True):
        np.testing.assert_array_equal(p.matches, q.matches)
        assert p.config == q.config
    # the geometry built from the batches' pairs is the one built by matching them here
    alt = np.asarray(s.altitudes)
    here = build_geometry(s.keypoints, s.image_descriptors, xy, alt, s.K.f)
    apart = build_geometry(s.keypoints, s.image_descriptors, xy, alt, s.K.f, known_pairs=known)
    assert here is not None and apart is not None
    np.testing.assert_array_equal(here[0].centres, apart[0].centres)
    np.testing.assert_array_equal(here[0].rotations, apart[0].rotations)
    for a, b in zip(here[1].points, apart[1].points, strict=True):
        np.testing.assert_array_equal(a, b)


def test_pairs_with_missing_tie_points_are_left_to_the_packing(surveyed, tmp_path):
    s, lat, lon, xy = surveyed
    stems = _write_ties(s, tmp_path)
    (tmp_path / "img2.kp.npy").unlink()
    planned = tiepairs.plan(lat, lon, list(s.altitudes))
    ids = list(range(len(xy)))
    tiepairs.match_batch(stems, planned, tmp_path / "pairs-000000.npz", image_ids=ids)
    known = tiepairs.load_results(tmp_path, ids)
    assert set(known) == {p for p in planned if 2 not in p}


def test_results_follow_their_images_in_the_map_order(surveyed, tmp_path):
    """A pair's result names its two images: it holds for a map that still has both, at
    their places in its order now (an image deleted before them moves them up; one added
    after them changes nothing), with its matches unchanged; not for one without them."""
    s, lat, lon, xy = surveyed
    stems = _write_ties(s, tmp_path)
    planned = tiepairs.plan(lat, lon, list(s.altitudes))
    ids = [10 + i for i in range(len(xy))]
    tiepairs.match_batch(stems, planned, tmp_path / "pairs-000000.npz", image_ids=ids)
    first = tiepairs.load_results(tmp_path, ids)
    assert set(first) == set(planned)
    assert set(tiepairs.load_results(tmp_path, ids + [99])) == set(planned)
    last = len(ids) - 1
    assert set(tiepairs.load_results(tmp_path, ids[:-1])) == \
        {p for p in planned if last not in p}
    # the first image replaced by another: its pairs go, the others stay where they are
    assert set(tiepairs.load_results(tmp_path, [5] + ids[1:])) == \
        {p for p in planned if 0 not in p}
    # the first image deleted: every other pair one place up, its matches as they were
    moved = tiepairs.load_results(tmp_path, ids[1:])
    assert set(moved) == {(a - 1, b - 1) for a, b in planned if a > 0}
    for (a, b), p in first.items():
        if a > 0:
            got = moved[(a - 1, b - 1)]
            assert (got is None) == (p is None)
            if p is not None:
                assert (got.a, got.b, got.config) == (a - 1, b - 1, p.config)
                np.testing.assert_array_equal(got.matches, p.matches)
    assert tiepairs.load_results(tmp_path / "nothing-here", ids) == {}


def test_keep_valid_gathers_what_holds_and_deletes_the_rest(surveyed, tmp_path):
    """Before a rebuild's batches, the results that still hold go into one file and the
    others are deleted; the rebuild plans only the pairs left, and afterwards the map's
    results are those of matching every pair afresh."""
    s, lat, lon, xy = surveyed
    stems = _write_ties(s, tmp_path)
    planned = tiepairs.plan(lat, lon, list(s.altitudes))
    ids = list(range(len(xy)))
    half = len(planned) // 2
    for k, batch in enumerate([planned[:half], planned[half:]]):
        tiepairs.match_batch(stems, batch, tmp_path / f"pairs-{k:06d}.npz", image_ids=ids)
    everything = tiepairs.load_results(tmp_path, ids)
    assert tiepairs.keep_valid(tmp_path, ids) == set(planned)
    assert [p.name for p in tmp_path.glob(tiepairs.RESULTS_GLOB)] == [tiepairs.KEPT]
    kept = tiepairs.load_results(tmp_path, ids)
    assert kept.keys() == everything.keys()
    for pair, p in everything.items():
        assert (p is None) == (kept[pair] is None)
        if p is not None:
            np.testing.assert_array_equal(p.matches, kept[pair].matches)
    stamp = (tmp_path / tiepairs.KEPT).stat().st_mtime_ns
    assert tiepairs.keep_valid(tmp_path, ids) == set(planned)      # nothing to gather
    assert (tmp_path / tiepairs.KEPT).stat().st_mtime_ns == stamp
    # the map's first image deleted: the pairs of the others are kept a place up, and the
    # places they were seeded at with them
    up = {(a - 1, b - 1) for a, b in planned if a > 0}
    assert tiepairs.keep_valid(tmp_path, ids[1:]) == up
    assert [p.name for p in tmp_path.glob(tiepairs.RESULTS_GLOB)] == [tiepairs.KEPT]
    assert set(tiepairs.load_results(tmp_path, ids[1:])) == up
    # image 0's pairs left the store with it
    assert set(tiepairs.load_results(tmp_path, ids)) == {p for p in planned if 0 not in p}
    # a full rebuild forgets the pairs that moved: every one of them here, so that the
    # map matches them seeded where they are now, as a fresh build would
    assert tiepairs.forget_moved(tmp_path) == len(up)
    assert tiepairs.keep_valid(tmp_path, ids[1:]) == set()
    assert tiepairs.forget_moved(tmp_path) == 0


def test_forget_moved_keeps_the_pairs_matched_where_they_are(surveyed, tmp_path):
    """Of a store whose pairs moved (an image deleted) and were then joined by pairs
    matched at their places (an image added after), a full rebuild forgets the moved ones
    alone; the others stay as they were."""
    s, lat, lon, xy = surveyed
    stems = _write_ties(s, tmp_path)
    planned = tiepairs.plan(lat, lon, list(s.altitudes))
    ids = list(range(len(xy)))
    tiepairs.match_batch(stems, [p for p in planned if 1 not in p],
                         tmp_path / "pairs-000000.npz", image_ids=ids)
    # image 1 deleted: the pairs after it move one place up; image 0's pairs with images
    # before it stay (none), those with images after move too
    rest = ids[:1] + ids[2:]
    kept = tiepairs.keep_valid(tmp_path, rest)
    stems_now = {k: stems[i] for k, i in enumerate(rest)}
    fresh = [(0, 1), (1, 2)]  # matched where they are: the images now at 0, 1 and 2
    fresh = [p for p in fresh if p not in kept]
    tiepairs.match_batch(stems_now, fresh, tmp_path / "pairs-000001.npz", image_ids=rest)
    before = tiepairs.load_results(tmp_path, rest)
    went = tiepairs.forget_moved(tmp_path)
    after = tiepairs.load_results(tmp_path, rest)
    assert went == len(kept) > 0
    assert set(after) == set(fresh)
    for pair in fresh:
        assert (after[pair] is None) == (before[pair] is None)


def test_an_empty_batch_round_trips(tmp_path):
    tiepairs.save_results([(0, 1, None)], tmp_path / "pairs-000000.npz", image_ids=[7, 8])
    assert tiepairs.load_results(tmp_path, [7, 8]) == {(0, 1): None}
    # written under a hidden name first: a file cut short by a dying worker is never read
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pairs-000000.npz"]
    (tmp_path / ".pairs-000001.npz").write_bytes(b"cut short")
    assert tiepairs.load_results(tmp_path, [7, 8]) == {(0, 1): None}


def test_results_round_trip_with_their_indices_and_configurations(tmp_path):
    done = [(0, 1, PairMatches(0, 1, np.array([[3, 5], [7, 2], [0, 9]], np.int64), 2)),
            (0, 2, None),
            (1, 2, PairMatches(1, 2, np.array([[4, 4]], np.int64), 6))]
    tiepairs.save_results(done, tmp_path / "pairs-000000.npz")
    back = tiepairs.read_results(tmp_path / "pairs-000000.npz")
    assert [(a, b, p is None) for a, b, p in back] == [(0, 1, False), (0, 2, True),
                                                        (1, 2, False)]
    for (_, _, want), (_, _, got) in zip(done, back, strict=True):
        if want is not None:
            assert (got.a, got.b, got.config) == (want.a, want.b, want.config)
            np.testing.assert_array_equal(got.matches, want.matches)


def test_results_of_another_format_are_ignored_and_matched_again(surveyed, tmp_path):
    """A failed build of the plane geometry left results of its own format (pixels and a
    homography per pair, no version): the retry reads none of them, and its batches match
    their pairs again."""
    s, lat, lon, xy = surveyed
    stems = _write_ties(s, tmp_path)
    planned = tiepairs.plan(lat, lon, list(s.altitudes))
    ids = list(range(len(xy)))
    old = tmp_path / "pairs-000000.npz"
    np.savez(old, a=np.array([0]), b=np.array([1]), verified=np.array([True]),
             counts=np.array([2]), pa=np.zeros((2, 2)), pb=np.ones((2, 2)),
             homographies=np.eye(3)[None])
    assert tiepairs.read_results(old) == []
    assert tiepairs.load_results(tmp_path, ids) == {}
    for version in (tiepairs.FORMAT - 1, tiepairs.FORMAT + 1):   # an earlier, a later one
        np.savez(old, format=np.array(version), a=np.array([0]), b=np.array([1]),
                 id_a=np.array([0]), id_b=np.array([1]), verified=np.array([False]),
                 counts=np.zeros(0, np.int64), matches=np.zeros((0, 2), np.int64),
                 configs=np.zeros(0, np.int64))
        assert tiepairs.load_results(tmp_path, ids) == {}
    assert tiepairs.keep_valid(tmp_path, ids) == set() and not old.exists()
    kept = tmp_path / tiepairs.KEPT                  # under the kept file's name too
    np.savez(kept, a=np.array([0]), b=np.array([1]))
    assert tiepairs.keep_valid(tmp_path, ids) == set()
    with np.load(kept) as z:                         # written again, empty, in this format
        assert int(z["format"]) == tiepairs.FORMAT and len(z["a"]) == 0
    kept.unlink()
    batch = planned[:3]
    assert tiepairs.match_batch({i: stems[i] for p in batch for i in p}, batch, old,
                                image_ids=ids) > 0
    known = tiepairs.load_results(tmp_path, ids)
    assert sorted(known) == batch
    assert all(p is None or p.matches.shape[1] == 2 for p in known.values())


def test_a_file_that_is_not_results_is_matched_again(surveyed, tmp_path):
    """A results file cut short or overwritten (not a results file at all) holds nothing:
    its pairs are matched again and the file goes, as one of another format."""
    s, lat, lon, xy = surveyed
    stems = _write_ties(s, tmp_path)
    planned = tiepairs.plan(lat, lon, list(s.altitudes))
    ids = list(range(len(xy)))
    tiepairs.match_batch(stems, planned[:3], tmp_path / "pairs-000000.npz", image_ids=ids)
    (tmp_path / "pairs-000001.npz").write_bytes(b"not an npz")
    assert set(tiepairs.load_results(tmp_path, ids)) == set(planned[:3])
    assert tiepairs.forget_moved(tmp_path) == 0
    assert tiepairs.keep_valid(tmp_path, ids) == set(planned[:3])
    assert [p.name for p in tmp_path.glob(tiepairs.RESULTS_GLOB)] == [tiepairs.KEPT]


def test_a_batch_that_ends_mid_pair_says_which_pair(surveyed, tmp_path, monkeypatch):
    s, lat, lon, xy = surveyed
    stems = _write_ties(s, tmp_path)
    planned = tiepairs.plan(lat, lon, list(s.altitudes))
    ids = [100 + i for i in range(len(xy))]
    out = tmp_path / "pairs-000000.npz"
    # a batch that finishes leaves no record of a pair
    tiepairs.match_batch(stems, planned[:2], out, image_ids=ids)
    assert tiepairs.crashed_pair(out) is None
    # one that ends in the third pair's matching (as a process COLMAP brings down does)
    real = tiepairs.match_pair
    calls = []

    def ends_on_the_third(*args, **kwargs):
        calls.append(args[:2])
        if len(calls) == 3:
            raise SystemExit("the process ends here")
        return real(*args, **kwargs)

    monkeypatch.setattr(tiepairs, "match_pair", ends_on_the_third)
    out2 = tmp_path / "pairs-000001.npz"
    with pytest.raises(SystemExit):
        tiepairs.match_batch(stems, planned[:5], out2, image_ids=ids)
    a, b = planned[2]
    assert not out2.exists()
    assert tiepairs.crashed_pair(out2) == (ids[a], ids[b])
    assert tiepairs.crashed_pair(out2) is None  # read once
    # the record is no results file: the pairs are matched again
    assert set(tiepairs.load_results(tmp_path, ids)) == set(planned[:2])


def test_the_map_store_keeps_the_pairs_reach_so_that_added_images_leave_the_pairs_as_they_were(
        tmp_path):
    """The first build decides how far apart two images may be for their tie points to be
    matched, from their spacing; images added later at another spacing would move that
    reach and add or drop pairs among the images the map held (every tile's inputs would
    change with them). With the map's store, an update plans them at the first build's
    reach; a store that keeps none (a full build forgets it) decides it again."""
    rng = np.random.default_rng(3)
    grid = np.stack(np.meshgrid(np.arange(8.0), np.arange(6.0)), -1).reshape(-1, 2) * 10.0
    held = grid + rng.normal(0.0, 1.0, grid.shape)
    # a denser flight 2 km off, lower down: it lowers the images' median spacing
    low = np.stack(np.meshgrid(np.arange(20.0), np.arange(10.0)), -1).reshape(-1, 2) * 2.0
    dense = low + [2000.0, 0.0] + rng.normal(0.0, 0.1, low.shape)
    both = np.vstack([held, dense])
    assert tie_reach(both) < tie_reach(held)
    n = len(held)
    store = KeptModels(tmp_path / "models", tuple(str(k) for k in range(n)))
    first = tie_pairs(held, kept=store)
    assert store.reach() == tie_reach(held)
    among_held = {p for p in tie_pairs(both) if p[1] < n}
    assert among_held < set(first)  # planned afresh, some of the map's pairs go
    grown = tie_pairs(both, kept=KeptModels(tmp_path / "models",
                                            tuple(str(k) for k in range(len(both)))))
    assert {p for p in grown if p[1] < n} == set(first)
    assert {p for p in grown if p[0] >= n} == {p for p in tie_pairs(both) if p[0] >= n}
    # forgotten (a full build): decided again from today's images
    (tmp_path / "models" / "reach.json").unlink()
    assert tie_pairs(both, kept=store) == tie_pairs(both)
    assert store.reach() == tie_reach(both)
    # a much sparser flight joins: its images would find too few neighbours within the
    # kept reach, which is decided again
    high = np.stack(np.meshgrid(np.arange(20.0), np.arange(15.0)), -1).reshape(-1, 2) * 80.0
    wide = np.vstack([both, high - [5000.0, 0.0]])
    assert tie_reach(wide) > REACH_GROWTH * store.reach()
    assert tie_pairs(wide, kept=store) == tie_pairs(wide)
    assert store.reach() == tie_reach(wide)
