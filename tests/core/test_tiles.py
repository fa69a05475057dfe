"""A large map's tiles reconstructed apart (as the engine's workers do) give the map that one
process reconstructing every tile gives, and the packing takes them up instead of
reconstructing them again."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tests.core.geometry.scene import F_TRUE, survey
from vloc.workers.core import tiepairs, tiles
from vloc.workers.core.geo import GeoOrigin, local_frame
from vloc.workers.core.geometry import TIE_NEIGHBOURS, build_geometry, sfm, tie_pairs, tiling
from vloc.workers.core.geometry import pairs as pairs_module
from vloc.workers.core.geometry.kept import KeptModels
from vloc.workers.core.geometry.pairs import match_pairs
from vloc.workers.core.sift import SiftFeatures
from vloc.workers.core.tiepoints import save_tie_points


@pytest.fixture(scope="module")
def surveyed(tmp_path_factory):
    """A 3 x 6 survey over relief, its tie points on disk and its verified pairs."""
    s = survey(np.random.default_rng(21), rows=3, cols=6, n_points=2500)
    folder = tmp_path_factory.mktemp("ties")
    stems = [str(folder / str(i)) for i in range(len(s.keypoints))]
    for kp, desc, stem in zip(s.keypoints, s.image_descriptors, stems, strict=True):
        save_tie_points(SiftFeatures(kp, desc), stem)
    pairs = match_pairs(s.keypoints, s.image_descriptors, tie_pairs(s.positions))
    return s, stems, pairs


@pytest.fixture
def small_tiles(monkeypatch):
    """Tiles of at most eight images, widened by one spacing, so that 18 make several."""
    monkeypatch.setattr(tiling, "MAX_TILE", 8)
    monkeypatch.setattr(tiling, "TILE_MARGIN", 1.0)


def test_spatial_tiles_cover_every_image_and_overlap():
    xy = np.array([[x * 10.0, y * 10.0] for y in range(16) for x in range(16)])
    parts = tiling.spatial_tiles(xy, 32)
    assert len(parts) == 8
    assert set(np.concatenate(parts).tolist()) == set(range(len(xy)))
    assert sum(len(p) for p in parts) > len(xy)  # neighbouring tiles share their edges
    # a core of 32 widened by three spacings either way
    assert all(32 < len(p) <= (4 + 6) * (8 + 6) for p in parts)
    assert [p.tolist() for p in tiling.spatial_tiles(xy, 1000)] == [list(range(len(xy)))]


def test_spatial_tiles_drop_a_tile_another_holds():
    # three images in a row, tiles of one: widened by three spacings each holds them all
    xy = np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 0.0]])
    assert [p.tolist() for p in tiling.spatial_tiles(xy, 1)] == [[0, 1, 2]]


def test_tiles_reconstructed_apart_are_the_map_of_one_process(surveyed, small_tiles,
                                                                 tmp_path, monkeypatch):
    s, stems, pairs = surveyed
    n = tiles.plan(tmp_path, pairs, s.positions, s.altitudes, F_TRUE, stems)
    assert n >= 3
    placed = [tiles.reconstruct(tmp_path, k) for k in range(n)]
    assert all(p > 0 for p in placed)
    known = tiles.load_results(tmp_path)
    assert len(known) == n
    whole = tiling.reconstruct(s.keypoints, pairs, s.positions, s.altitudes, F_TRUE)

    def refuse(*args, **kwargs):
        raise AssertionError("a tile reconstructed elsewhere was reconstructed again")

    monkeypatch.setattr(tiling, "tile_models", refuse)
    taken = tiling.reconstruct(s.keypoints, pairs, s.positions, s.altitudes, F_TRUE,
                            known_tiles=known)
    np.testing.assert_array_equal(taken.centres, whole.centres)
    np.testing.assert_array_equal(taken.rotations, whole.rotations)
    for i in range(len(s.centres)):
        np.testing.assert_array_equal(taken.points[i], whole.points[i])
    # and the tiles' cameras are where the survey flew
    assert taken.placed.mean() > 0.9
    err = np.linalg.norm(taken.centres[taken.placed] - s.centres[taken.placed], axis=1)
    assert np.median(err) < 1.0


def test_tile_workers_judge_a_tile_by_the_core_the_packing_judges_it_by(
        surveyed, small_tiles, tmp_path, monkeypatch):
    """A tile reconstructed by a worker is given its core, as the packing's own
    reconstruction of it is: a grown tile is judged by the new images of its core
    (:func:`~vloc.workers.core.geometry.sfm._grew_well`) wherever it is reconstructed."""
    s, stems, pairs = surveyed
    n = tiles.plan(tmp_path, pairs, s.positions, s.altitudes, F_TRUE, stems)
    plan = tiling.map_tiles(s.positions, None)
    assert n == len(plan) >= 3
    seen = []
    real = tiles.tile_models

    def spy(*args, **kwargs):
        seen.append((np.asarray(args[4]).tolist(), np.asarray(kwargs["core"]).tolist()))
        return real(*args, **kwargs)

    monkeypatch.setattr(tiles, "tile_models", spy)
    for k in range(n):
        tiles.reconstruct(tmp_path, k)
    assert seen == [(t.members.tolist(), t.core.tolist()) for t in plan]
    assert all(len(core) < len(members) for members, core in seen)


def test_a_tile_done_for_other_inputs_is_redone(surveyed, small_tiles, tmp_path):
    s, stems, pairs = surveyed
    n = tiles.plan(tmp_path, pairs, s.positions, s.altitudes, F_TRUE, stems)
    tiles.reconstruct(tmp_path, 0)
    before = set(tiles.load_results(tmp_path))
    # the same folder planned again with another focal length: tile 0's result is stale
    assert tiles.plan(tmp_path, pairs, s.positions, s.altitudes, 1.1 * F_TRUE, stems) == n
    tiles.reconstruct(tmp_path, 0)
    after = set(tiles.load_results(tmp_path))
    assert len(after) == 1 and after != before
    # and kept as it is when nothing changed
    stamp = (tmp_path / tiles.RESULT.format(0)).stat().st_mtime_ns
    tiles.reconstruct(tmp_path, 0)
    assert (tmp_path / tiles.RESULT.format(0)).stat().st_mtime_ns == stamp


def test_a_tile_done_with_other_mapper_settings_is_redone(surveyed, small_tiles, tmp_path,
                                                          monkeypatch):
    s, stems, pairs = surveyed
    tiles.plan(tmp_path, pairs, s.positions, s.altitudes, F_TRUE, stems)
    tiles.reconstruct(tmp_path, 0)
    stamp = (tmp_path / tiles.RESULT.format(0)).stat().st_mtime_ns
    before = set(tiles.load_results(tmp_path))
    # an earlier build's tile, kept in the map's folder, after the mapper's settings changed
    monkeypatch.setattr(sfm, "MIN_POSE_INLIER_RATIO", 0.3)
    assert set(tiles.load_results(tmp_path)) == before
    tiles.reconstruct(tmp_path, 0)
    assert (tmp_path / tiles.RESULT.format(0)).stat().st_mtime_ns != stamp
    assert len(set(tiles.load_results(tmp_path))) == 1
    assert set(tiles.load_results(tmp_path)) != before


def test_tiles_of_an_earlier_plan_go_when_a_plan_has_fewer(surveyed, small_tiles, tmp_path,
                                                           monkeypatch):
    """A map's store outlives its builds: tiles an earlier plan had beyond the new plan's
    are deleted, and a map built whole keeps no tile at all."""
    s, stems, pairs = surveyed
    n = tiles.plan(tmp_path, pairs, s.positions, s.altitudes, F_TRUE, stems)
    assert n >= 2
    tiles.reconstruct(tmp_path, n - 1)
    assert (tmp_path / tiles.RESULT.format(n - 1)).is_file()
    monkeypatch.setattr(tiling, "MAX_TILE", 10 ** 6)
    assert tiles.plan(tmp_path, pairs, s.positions, s.altitudes, F_TRUE, stems) == 0
    assert not list(tmp_path.glob("tile-*"))


def test_a_small_map_is_not_tiled(surveyed, tmp_path):
    s, stems, pairs = surveyed
    assert tiles.plan(tmp_path, pairs, s.positions, s.altitudes, F_TRUE, stems) == 0
    assert tiles.load_results(tmp_path) == {}


def test_the_packing_takes_up_every_tile_the_build_reconstructed(tmp_path, monkeypatch):
    """The service's order: pairs planned from the images' WGS84 tags and matched in
    batches, tiles planned from those pairs and reconstructed, then the packing's geometry,
    which must match no pair and reconstruct no tile again. (The plan once took each
    image's 16 nearest where the packing kept 12: over a survey this dense the extra pairs
    verify, no tile's key was the packing's, and every tile was reconstructed twice.)"""
    # tiles larger than an image's neighbours, so that a tile holds pairs beyond them
    monkeypatch.setattr(tiling, "MAX_TILE", 16)
    monkeypatch.setattr(tiling, "TILE_MARGIN", 1.0)
    s = survey(np.random.default_rng(8), rows=4, cols=8, spacing=9.0, n_points=2500)
    stems = [str(tmp_path / f"img{i}") for i in range(len(s.keypoints))]
    for kp, desc, stem in zip(s.keypoints, s.image_descriptors, stems, strict=True):
        save_tie_points(SiftFeatures(kp, desc), stem)
    lat, lon = GeoOrigin(42.0, -76.5, 300.0).to_wgs84(s.positions[:, 0], s.positions[:, 1])
    _, xy, alt = local_frame(lat, lon, list(s.altitudes))
    planned = tiepairs.plan(lat, lon, list(s.altitudes))
    # the neighbour limit, not the reach, decides which pairs are tried
    assert max(np.bincount(np.ravel(planned))) > TIE_NEIGHBOURS
    ids = list(range(len(xy)))
    for k in range(0, len(planned), 10):
        batch = planned[k:k + 10]
        tiepairs.match_batch({i: stems[i] for p in batch for i in p}, batch,
                             tmp_path / f"pairs-{k:06d}.npz", image_ids=ids)
    known_pairs = tiepairs.load_results(tmp_path, ids)
    verified = [p for _, p in sorted(known_pairs.items()) if p is not None]
    far = [p for p in verified if np.hypot(*(xy[p.a] - xy[p.b])) > 2.5 * 9.0]
    assert far, "pairs beyond the nearest neighbours verify"
    n = tiles.plan(tmp_path, verified, xy, alt, F_TRUE, stems)
    assert n >= 2
    for k in range(n):
        tiles.reconstruct(tmp_path, k)

    def refuse(*args, **kwargs):
        raise AssertionError("the packing matched a pair or reconstructed a tile again")

    monkeypatch.setattr(pairs_module, "match_pair", refuse)
    monkeypatch.setattr(tiling, "tile_models", refuse)
    built = build_geometry(s.keypoints, s.image_descriptors, xy, alt, F_TRUE,
                           known_pairs=known_pairs, known_tiles=tiles.load_results(tmp_path))
    assert built is not None and built[1].placed.mean() > 0.9


def test_each_tile_keeps_its_model_and_grows_from_it_when_its_inputs_change(
        surveyed, small_tiles, tmp_path, monkeypatch):
    import pycolmap

    s, stems, pairs = surveyed
    n = tiles.plan(tmp_path, pairs, s.positions, s.altitudes, F_TRUE, stems)
    for k in range(n):
        tiles.reconstruct(tmp_path, k)
    models = tmp_path / tiles.MODELS
    known = tiles.load_results(tmp_path)
    assert {p.name for p in models.iterdir()} == {k for k, m in known.items() if m}
    # the packing keeps the models of the map it packs, no other
    (models / "stale").mkdir()
    kept = KeptModels(models, tuple(Path(stem).name for stem in stems))
    tiling.reconstruct(s.keypoints, pairs, s.positions, s.altitudes, F_TRUE,
                       known_tiles=known, kept=kept)
    assert "stale" not in {p.name for p in models.iterdir()}
    assert {k for k, m in known.items() if m} <= {p.name for p in models.iterdir()}
    # a pair of tile 0 lost (its inputs changed): the tile grows from its kept model
    inside = tiling.spatial_tiles(s.positions, tiling.MAX_TILE)[0]
    lost = tiling.tile_pairs(pairs, inside)[-1]
    tiles.plan(tmp_path, [p for p in pairs if p is not lost], s.positions, s.altitudes,
               F_TRUE, stems)
    calls = []
    real = pycolmap.incremental_mapping

    def spy(*args, input_path="", **kw):
        calls.append(str(input_path))
        return real(*args, input_path=input_path, **kw)

    monkeypatch.setattr(pycolmap, "incremental_mapping", spy)
    assert tiles.reconstruct(tmp_path, 0) > 0
    assert len(calls) == 1 and calls[0] != ""


def _grid(nx: int, ny: int, step: float = 10.0) -> np.ndarray:
    return np.array([[x * step, y * step] for y in range(ny) for x in range(nx)])


def test_a_map_built_again_is_cut_where_it_was():
    xy = _grid(16, 16)
    first = tiling.plan_tiles(xy, 32)
    assert [t.members.tolist() for t in first] == [p.tolist() for p in
                                                  tiling.spatial_tiles(xy, 32)]
    assert sorted(np.concatenate([t.core for t in first]).tolist()) == list(range(len(xy)))
    # planned again from itself: the same tiles
    again = tiling.plan_tiles(xy, 32, previous=first)
    assert [(t.core.tolist(), t.members.tolist()) for t in again] == \
        [(t.core.tolist(), t.members.tolist()) for t in first]
    # six images added in one corner (after the others, as a map orders added images):
    # they join the core of their nearest image; tiles they do not reach are unchanged,
    # those they reach keep every image they had
    added = np.array([[1.0 + k, 2.0] for k in range(6)])
    grown = tiling.plan_tiles(np.vstack([xy, added]), 32, previous=first)
    assert len(grown) == len(first)
    new = set(range(len(xy), len(xy) + 6))
    changed = 0
    for before, after in zip(first, grown, strict=True):
        gained = set(after.members.tolist()) - set(before.members.tolist())
        assert set(before.members.tolist()) <= set(after.members.tolist())
        assert gained <= new
        changed += bool(gained)
        assert set(after.core.tolist()) - set(before.core.tolist()) <= new
    assert 1 <= changed < len(first)
    assert sorted(np.concatenate([t.core for t in grown]).tolist()) == \
        list(range(len(xy) + 6))
    # a fresh cut would have moved tiles these images are nowhere near
    fresh = tiling.plan_tiles(np.vstack([xy, added]), 32)
    assert [t.members.tolist() for t in fresh] != [t.members.tolist() for t in grown]


def test_images_grown_past_the_limit_make_tiles_of_their_own_and_the_others_stay():
    xy = _grid(16, 16)
    first = tiling.plan_tiles(xy, 32)
    # forty images inside the first tile's core, whose 32 make it full: past the slack,
    # they make tiles of their own beside it (its kept model still fits it), the others stay
    assert 32 + 40 > tiling.GROWTH_SLACK * 32 >= 32 + 6
    assert tiling.NEW_TILE_SHARE * 32 <= 40
    lo, hi = xy[first[0].core].min(axis=0), xy[first[0].core].max(axis=0)
    rng = np.random.default_rng(0)
    added = lo + rng.random((40, 2)) * (hi - lo)
    grown = tiling.plan_tiles(np.vstack([xy, added]), 32, previous=first)
    assert len(grown) > len(first)
    untouched = [t for t in first[1:]
                 if not np.any(np.all((added >= xy[t.members].min(axis=0))
                                      & (added <= xy[t.members].max(axis=0)), axis=1))]
    kept = {tuple(t.members.tolist()) for t in grown}
    assert untouched and all(tuple(t.members.tolist()) in kept for t in untouched)
    assert all(len(t.core) <= 32 for t in grown)
    # the first tile stays as it was: its kept model is taken up
    (same,) = [t for t in grown if t.core.tolist() == first[0].core.tolist()]
    assert same.members.tolist() == first[0].members.tolist()
    new = set(range(len(xy), len(xy) + 40))
    assert {i for t in grown for i in t.core.tolist()} >= new
    assert all(set(t.core.tolist()) <= new for t in grown
               if not set(t.core.tolist()) & set(range(len(xy))))


def test_a_core_grown_past_the_limit_by_a_few_images_is_halved():
    xy = _grid(16, 16)
    first = tiling.plan_tiles(xy, 32)
    lo, hi = xy[first[0].core].min(axis=0), xy[first[0].core].max(axis=0)
    rng = np.random.default_rng(1)
    # six images join the full first tile (38, within the slack), then three more: past
    # it, but too few to reconstruct apart, so the grown core is halved
    some = lo + rng.random((6, 2)) * (hi - lo)
    grown = tiling.plan_tiles(np.vstack([xy, some]), 32, previous=first)
    assert len(grown[0].core) == 38
    few = lo + rng.random((3, 2)) * (hi - lo)
    assert tiling.NEW_TILE_SHARE * 32 > 3 and tiling.GROWTH_SLACK * 32 < 41
    again = tiling.plan_tiles(np.vstack([xy, some, few]), 32, previous=grown)
    assert len(again) == len(grown) + 1
    assert all(len(t.core) <= 32 for t in again)
    assert not any(t.core.tolist() == grown[0].core.tolist() for t in again)


def test_kept_tiles_go_by_name_and_leave_deleted_images_out(tmp_path):
    names = tuple(f"id{i}" for i in range(6))
    kept = KeptModels(tmp_path, names)
    assert kept.tiles() is None
    kept.save_tiles([(np.array([0, 1, 2]), np.array([0, 1, 2, 3])),
                     (np.array([3, 4, 5]), np.array([2, 3, 4, 5]))])
    # image id2 deleted: the others move up a place in the map's order
    later = KeptModels(tmp_path, names[:2] + names[3:])
    (a_core, a_members), (b_core, b_members) = later.tiles()
    assert (a_core.tolist(), a_members.tolist()) == ([0, 1], [0, 1, 2])
    assert (b_core.tolist(), b_members.tolist()) == ([2, 3, 4], [2, 3, 4])
    kept.keep_only([])  # the models go; the tiles stay
    assert later.tiles() is not None
