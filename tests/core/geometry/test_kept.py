"""COLMAP's models kept from build to build: images added to a map are registered into the
cameras it has, which stay where they were; a model that no longer fits is not grown."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from tests.core.geometry.scene import (
    F_TRUE,
    Survey,
    exact_pairs,
    similarity_residual,
    survey,
)
from vloc.workers.core.geometry import sfm
from vloc.workers.core.geometry.kept import (
    CONTEXT_FILE,
    EXTEND_MIN_SHARE,
    ORDER_FILE,
    KeptModels,
    read_order,
)
from vloc.workers.core.geometry.models import TileModel
from vloc.workers.core.geometry.tiling import reconstruct


def _names(n: int) -> tuple[str, ...]:
    return tuple(f"img{1000 + i}" for i in range(n))


def _build(s: Survey, n: int, kept: KeptModels | None = None, *, drop: int | None = None):
    """The structure of the survey's first ``n`` images (without image ``drop``)."""
    use = [i for i in range(n) if i != drop]
    index = {i: k for k, i in enumerate(use)}
    pairs = [dataclasses.replace(p, a=index[p.a], b=index[p.b]) for p in exact_pairs(s)
             if p.a in index and p.b in index]
    return reconstruct([s.keypoints[i] for i in use], pairs, s.positions[use],
                       s.altitudes[use], F_TRUE, kept=kept)


@pytest.fixture
def mapping_calls(monkeypatch):
    """Every call of COLMAP's mapper: (its input model, whether it holds that model's
    cameras)."""
    import pycolmap

    calls = []
    real = pycolmap.incremental_mapping

    def spy(database, images, out, options, input_path="", **kw):
        calls.append((str(input_path), options.fix_existing_frames))
        return real(database, images, out, options, input_path=input_path, **kw)

    monkeypatch.setattr(pycolmap, "incremental_mapping", spy)
    return calls


def test_added_images_join_the_kept_cameras_which_stay_where_they_were(tmp_path,
                                                                        mapping_calls):
    s = survey(np.random.default_rng(21), rows=4, cols=4)
    first = _build(s, 12, KeptModels(tmp_path, _names(12)))
    assert first.placed.all()
    entries = [p for p in tmp_path.iterdir() if p.is_dir()]
    assert len(entries) == 1 and mapping_calls == [("", False)]
    order = read_order(entries[0])
    assert sorted(order) == sorted(_names(12))

    grown = _build(s, 16, KeptModels(tmp_path, _names(16)))
    # the second build started from the kept model, its cameras held
    assert mapping_calls[1][0] != "" and mapping_calls[1][1] is True
    assert len(mapping_calls) == 2
    assert grown.placed.all() and grown.models == 1
    # the kept cameras did not move relative to one another
    assert similarity_residual(first.centres, grown.centres[:12]) < 1e-6
    # the added ones are where they are (exact keypoints, exact tags)
    np.testing.assert_allclose(grown.centres[12:], s.centres[12:], atol=0.05)
    # the store holds this build's model alone, its database listing the kept images first
    entries = [p for p in tmp_path.iterdir() if p.is_dir()]
    assert len(entries) == 1
    assert read_order(entries[0])[:len(order)] == order
    assert sorted(read_order(entries[0])) == sorted(_names(16))


def test_a_kept_model_that_lost_an_image_grows_without_it(tmp_path, mapping_calls):
    """An image deleted from the map leaves the kept model: the others' cameras are held
    where they were, the 3-D points it alone saw go, and no camera is reconstructed
    anew."""
    s = survey(np.random.default_rng(22), rows=3, cols=4)
    names = _names(12)
    first = _build(s, 12, KeptModels(tmp_path, names))
    assert first.placed.all()
    (entry,) = [p for p in tmp_path.iterdir() if p.is_dir()]
    order = read_order(entry)
    # image 5 deleted: the map's other images keep their names
    kept = KeptModels(tmp_path, names[:5] + names[6:])
    again = _build(s, 12, kept, drop=5)
    assert mapping_calls[-1][0] != "" and mapping_calls[-1][1] is True  # grown, held
    assert len(mapping_calls) == 2
    assert again.placed.all() and len(again.centres) == 11
    rest = np.r_[0:5, 6:12]
    assert similarity_residual(first.centres[rest], again.centres) < 1e-6
    # the store holds the grown model, its database the kept images in their old order
    (entry,) = [p for p in tmp_path.iterdir() if p.is_dir()]
    assert read_order(entry) == [n for n in order if n != names[5]]
    # and the map built from it again, with nothing changed, is taken up as it is
    twice = _build(s, 12, kept, drop=5)
    assert len(mapping_calls) == 2
    np.testing.assert_allclose(twice.centres, again.centres, atol=1e-9)


def test_without_images_keeps_the_others_poses_and_their_shared_points(tmp_path):
    """The model copied without some images: each kept image renumbered, with its pose and
    keypoints; a 3-D point keeps the observations of the kept cameras, and goes where
    fewer than two remain."""
    import pycolmap

    from vloc.workers.core.geometry.kept import MODEL_DIR, without_images

    s = survey(np.random.default_rng(23), rows=3, cols=3)
    _build(s, 9, KeptModels(tmp_path, _names(9)))
    (entry,) = [p for p in tmp_path.iterdir() if p.is_dir()]
    rec = pycolmap.Reconstruction(str(entry / MODEL_DIR.format(0)))
    ids = sorted(rec.images)
    gone = set(ids[2:7])
    renumber = {old: k + 1 for k, old in enumerate(i for i in ids if i not in gone)}
    out = without_images(rec, renumber)
    assert sorted(out.images) == list(range(1, len(renumber) + 1))
    for old, new in renumber.items():
        a, b = rec.images[old], out.images[new]
        assert a.name == b.name and a.has_pose == b.has_pose
        np.testing.assert_array_equal(a.cam_from_world().matrix(), b.cam_from_world().matrix())
        np.testing.assert_array_equal([p.xy for p in a.points2D], [p.xy for p in b.points2D])
    # the slow obvious reference: every point's observations by the kept images
    want = []
    for point in rec.points3D.values():
        track = sorted((renumber[e.image_id], e.point2D_idx) for e in point.track.elements
                       if e.image_id not in gone)
        if len(track) >= 2:
            want.append((tuple(np.round(point.xyz, 9)), tuple(track)))
    got = [(tuple(np.round(p.xyz, 9)), tuple(sorted((e.image_id, e.point2D_idx)
                                                    for e in p.track.elements)))
           for p in out.points3D.values()]
    assert sorted(got) == sorted(want)
    assert 0 < len(want) < len(rec.points3D)  # some seen by fewer than two kept cameras
    # each kept observation is on its image's keypoint
    for p3 in out.points3D.values():
        for e in p3.track.elements:
            assert out.images[e.image_id].points2D[e.point2D_idx].has_point3D()


def _entry(folder, name: str, order: list[str], context: str = "c") -> None:
    (folder / name).mkdir(parents=True)
    (folder / name / ORDER_FILE).write_text("".join(f"{n}\n" for n in order))
    (folder / name / CONTEXT_FILE).write_text(context)


def test_base_for_takes_the_largest_kept_model_inside_the_tile(tmp_path):
    names = tuple(f"n{i}" for i in range(10))
    kept = KeptModels(tmp_path, names)
    _entry(tmp_path, "small", ["n0", "n1", "n2"])
    _entry(tmp_path, "large", ["n3", "n0", "n1", "n2", "n4"])
    _entry(tmp_path, "outside", ["n0", "n1", "n2", "n3", "n4", "n5", "n6"])
    _entry(tmp_path, ".writing", ["n0", "n1", "n2", "n3", "n4", "n5"])
    _entry(tmp_path, "other settings", ["n0", "n1", "n2", "n3", "n4", "n5"], context="d")
    assert kept.base_for(np.arange(6), tied=6, context="c") == tmp_path / "large"
    assert kept.base_for(np.arange(6), tied=6, context="d") == tmp_path / "other settings"
    # a tile of new images mostly: none fits
    assert EXTEND_MIN_SHARE * 12 > 5
    assert kept.base_for(np.arange(6), tied=12, context="c") is None
    assert kept.base_for(np.arange(10), tied=10, context="c") == tmp_path / "outside"
    assert kept.base_for(np.array([1, 2, 3, 4]), tied=4, context="c") is None
    assert kept.base_for(np.arange(10), tied=10, context="e") is None
    kept.keep_only(["small", "large"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["large", "small"]
    KeptModels(tmp_path / "absent", names).keep_only([])  # nothing kept yet: nothing to do


def test_similarity_residual_known_answers():
    rng = np.random.default_rng(3)
    a = rng.normal(size=(8, 3))
    c, s_ = np.cos(0.4), np.sin(0.4)
    R = np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]])
    assert similarity_residual(a, 2.5 * a @ R.T + [3.0, -1.0, 7.0]) < 1e-9
    moved = a.copy()
    moved[0] += [1.0, 0.0, 0.0]
    assert similarity_residual(a, moved) > 0.3


def _run_placing(order: int, held: int, registered: int, placed: int) -> sfm._Run:
    """A grown run: ``held`` images in the kept model, ``registered`` of them placed, and
    ``order - held`` new ones, the first ``placed - registered`` of which are placed."""
    images = np.r_[0:registered, held:held + placed - registered]
    model = TileModel(images, np.zeros((len(images), 3, 3)), np.zeros((len(images), 3)),
                          [], [], np.zeros(4), 0.0)
    return sfm._Run([model], None, list(range(order)), base=(held, registered))


def test_a_model_grew_well_when_it_placed_its_share_of_the_new_images():
    # lewis-uav's first two thirds: 14 of 18 placed; 10 added, of which 6 placed
    assert not sfm._grew_well(_run_placing(28, 18, 14, 20))
    assert sfm._grew_well(_run_placing(28, 18, 14, 22))  # 8 of 10: one short of 14/18
    # seneca-uav: 63 of 70 in the kept model, 48 added, 114 placed in all
    assert sfm._grew_well(_run_placing(118, 70, 63, 114))
    assert sfm._grew_well(_run_placing(70, 70, 63, 60))  # nothing new: nothing to judge


def test_a_tile_grew_well_when_it_placed_its_share_of_the_new_images_of_its_core():
    """A tile of 100 kept images, all placed, gains 40 along its edge: 10 in its core, 9
    of them placed, and 30 in its margin, 20 placed. Judged over all 40 (29 placed, 39
    asked) it would be reconstructed whole; over its core's (9 of 10) it grew well."""
    run = _run_placing(140, 100, 100, 129)
    assert not sfm._grew_well(run)
    core = np.ones(140, bool)
    core[109:130] = False  # margin: 109..128 placed, 129 not,
    core[131:140] = False  # and 131..139 not: the core's new images are 100..108 and 130
    assert int(core[100:].sum()) == 10
    assert sfm._grew_well(run, core)
    core[:] = True
    assert not sfm._grew_well(run, core)  # every image in the core: as without one
    # the core's new images placed too thinly: reconstructed whole
    core[:] = False
    core[128:140] = True  # 128 placed, 129..139 not
    assert not sfm._grew_well(run, core)


def test_a_large_tile_grew_well_when_it_placed_half_its_share_of_the_new_images():
    """A kept model of more than LARGE_MODEL cameras is reconstructed whole only where it
    took in fewer than half the new images it would place at its own rate: the images it
    leaves out are reconstructed apart, at a fraction of a whole run's cost."""
    held = sfm.LARGE_MODEL + 50
    registered = held - 10
    share = registered / held * 40  # 40 new images
    enough = int(np.ceil(sfm.LARGE_BASE_SHARE * share))
    assert enough < share - 1  # the small models' rule would reconstruct it whole
    assert sfm._grew_well(_run_placing(held + 40, held, registered, registered + enough))
    assert not sfm._grew_well(_run_placing(held + 40, held, registered,
                                           registered + enough - 1))
    # a small kept model placing as many is reconstructed whole
    small = sfm.LARGE_MODEL
    assert not sfm._grew_well(_run_placing(small + 40, small, small,
                                           small + int(np.ceil(sfm.LARGE_BASE_SHARE * 40))))


def test_a_model_that_grew_badly_is_reconstructed_whole_too_and_the_better_kept(
        tmp_path, mapping_calls, monkeypatch):
    s = survey(np.random.default_rng(23), rows=4, cols=4)
    first = _build(s, 12, KeptModels(tmp_path, _names(12)))
    monkeypatch.setattr(sfm, "_grew_well", lambda run, core=None: False)
    grown = _build(s, 16, KeptModels(tmp_path, _names(16)))
    # grown from the kept model, then reconstructed whole: both place every image, and
    # the grown one wins the tie, its kept cameras where they were
    assert [call[0] != "" for call in mapping_calls[1:]] == [True, False]
    assert grown.placed.all()
    assert similarity_residual(first.centres, grown.centres[:12]) < 1e-6


def test_a_tile_of_the_same_inputs_is_only_aligned_again(tmp_path, mapping_calls):
    """A map's frame moves with its centroid when images are added elsewhere: a tile whose
    images and matches did not change takes its kept models up, aligned to today's GPS,
    without running COLMAP."""
    s = survey(np.random.default_rng(24), rows=3, cols=4)
    first = _build(s, 12, KeptModels(tmp_path, _names(12)))
    shift = np.array([120.0, -40.0])
    pairs = exact_pairs(s)
    again = reconstruct(s.keypoints, pairs, s.positions + shift, s.altitudes, F_TRUE,
                        kept=KeptModels(tmp_path, _names(12)))
    assert len(mapping_calls) == 1
    np.testing.assert_allclose(again.centres, first.centres + [*shift, 0.0], atol=1e-6)
    np.testing.assert_allclose(again.points[3], first.points[3] + [*shift, 0.0], atol=1e-6)
    (entry,) = [p for p in tmp_path.iterdir() if p.is_dir()]  # kept under its new key
    # another match changes the inputs: COLMAP runs (from the kept model)
    changed = pairs[:-1]
    reconstruct(s.keypoints, changed, s.positions, s.altitudes, F_TRUE,
                kept=KeptModels(tmp_path, _names(12)))
    assert len(mapping_calls) == 2 and mapping_calls[1][0] != ""
