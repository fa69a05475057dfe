"""The map's structure from motion (COLMAP's incremental mapper, aligned to GPS), on synthetic
scenes with exact keypoints: the cameras and 3-D points come back where they are."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from tests.core.geometry.scene import (
    F_TRUE,
    Survey,
    exact_pairs,
    rotation_angle_deg,
    street,
    survey,
)
from vloc.workers.core.geometry import sfm, tiling
from vloc.workers.core.geometry.models import COLMAP_SCALE, tags
from vloc.workers.core.geometry.pairs import PairMatches
from vloc.workers.core.geometry.sfm import to_colmap_pixels
from vloc.workers.core.geometry.tiling import (
    left_out_models,
    reconstruct,
    tied_groups,
    tile_models,
)


def _point_errors(s: Survey, st) -> np.ndarray:
    """Distance of every reconstructed observation's 3-D point from its true point."""
    return np.concatenate([np.linalg.norm(st.points[i] - s.truth(i, st.observations[i]), axis=1)
                           for i in np.flatnonzero(st.placed)])


def _reconstruct(s: Survey, *, positions=None, altitudes=None, focal_px=F_TRUE, seed=0):
    return reconstruct(s.keypoints, exact_pairs(s),
                       s.positions if positions is None else positions,
                       s.altitudes if altitudes is None else altitudes, focal_px, seed=seed)


def _check_exact(s: Survey, st, *, tol=0.02):
    """Exact keypoints and exact tags: the scene itself, to round-off and COLMAP's
    convergence."""
    assert st.placed.all() and st.models == 1
    np.testing.assert_allclose(st.centres, s.centres, atol=tol)
    assert max(rotation_angle_deg(a, b) for a, b in zip(st.rotations, s.rotations,
                                                         strict=True)) < 0.05
    err = _point_errors(s, st)
    # most keypoints that other images see become observations
    assert len(err) > 0.5 * sum(len(k) for k in s.keypoints)
    assert err.max() < 5 * tol
    assert st.intrinsics.f == pytest.approx(F_TRUE, rel=1e-3)
    assert (st.intrinsics.cx, st.intrinsics.cy) == (159.5, 119.5)
    assert abs(st.k1) < 1e-3 and st.residual_px < 0.01
    assert st.gps_rms_h < tol and st.gps_rms_v < tol


def test_to_colmap_pixels_known_answer():
    # 0 at the first pixel's centre, scaled to the tie points' resolution: COLMAP puts 0
    # at its corner
    px = np.array([[0.0, 0.0, 3.0, 0.0], [319.0, 239.0, 3.0, 0.0], [159.5, 119.5, 1.0, 0.0]])
    np.testing.assert_array_equal(to_colmap_pixels(px),
                                  [[1.0, 1.0], [639.0, 479.0], [320.0, 240.0]])
    assert COLMAP_SCALE == 2.0


def test_reconstruct_a_nadir_survey_over_hills_and_buildings():
    s = survey(np.random.default_rng(0))
    assert np.ptp(s.points[:, 2]) > 12.0  # relief, not a plane
    st = _reconstruct(s)
    _check_exact(s, st)
    # the same inputs give the same map
    again = _reconstruct(s)
    np.testing.assert_array_equal(again.centres, st.centres)
    np.testing.assert_array_equal(again.points[3], st.points[3])


def test_a_large_reconstruction_adjusts_lighter_and_still_recovers_the_scene(monkeypatch):
    import pycolmap

    seen = []
    real = pycolmap.incremental_mapping

    def spy(database, images, out, options, **kw):
        seen.append(options.todict())
        return real(database, images, out, options, **kw)

    monkeypatch.setattr(pycolmap, "incremental_mapping", spy)
    s = survey(np.random.default_rng(0))
    _reconstruct(s)
    defaults = pycolmap.IncrementalPipelineOptions().todict()
    assert all(seen[0][k] == defaults[k] for k in sfm.LARGE_BA)
    assert not seen[0]["mapper"]["ba_global_ignore_redundant_points3D"]
    # the same survey counted as a large map: COLMAP's FAQ options, the same scene
    monkeypatch.setattr(sfm, "LARGE_MODEL", len(s.keypoints) - 1)
    seen.clear()
    st = _reconstruct(s)
    assert seen and all(seen[0][k] == pytest.approx(v) for k, v in sfm.LARGE_BA.items())
    assert seen[0]["mapper"]["ba_global_ignore_redundant_points3D"]
    _check_exact(s, st)


def test_reconstruct_finds_the_focal_length_without_exif_over_relief():
    # None starts from a 65 degree lens (251 px) where the truth is 60 (277 px): relief
    # tells focal length and height apart
    s = survey(np.random.default_rng(1))
    st = _reconstruct(s, focal_px=None)
    assert st.intrinsics.f == pytest.approx(F_TRUE, rel=2e-3)
    _check_exact(s, st)


def test_reconstruct_through_gps_noise():
    # any heading: the cameras' level right axes pin both of the model's tilts
    s = survey(np.random.default_rng(3), rows=3, cols=4, headings="random")
    rng = np.random.default_rng(7)
    gps = s.positions + rng.normal(0.0, 0.5, s.positions.shape)
    alt = s.altitudes + rng.normal(0.0, 2.0, len(s))
    st = _reconstruct(s, positions=gps, altitudes=alt)
    assert st.placed.all()
    err = st.centres - s.centres
    assert np.abs(err[:, :2]).max() < 0.6
    # the altitudes' mean is what places the model vertically: 12 tags at 2 m, 0.6 m
    assert np.abs(err[:, 2]).max() < 2.0 and np.ptp(err[:, 2]) < 0.5
    # the points: as far off as the cameras, lifted with them
    d = np.concatenate([st.points[i] - s.truth(i, st.observations[i]) for i in range(len(s))])
    assert np.percentile(np.linalg.norm(d[:, :2], axis=1), 95) < 1.0
    assert np.percentile(np.abs(d[:, 2] - np.median(err[:, 2])), 95) < 0.5
    assert st.gps_rms_h == pytest.approx(
        np.sqrt(np.mean(np.sum((st.centres[:, :2] - gps) ** 2, axis=1))))
    assert st.gps_rms_h < 0.7 and st.gps_rms_v < 2.5


def test_reconstruct_a_survey_whose_gps_altitudes_drift_100_m():
    """The tags' altitudes drift by 100 m from the first image to the last: the model stays
    level (its altitudes lifted by about the drift's middle), horizontally where it is."""
    s = survey(np.random.default_rng(4), rows=3, cols=4, headings="random")
    drift = np.linspace(0.0, 100.0, len(s))
    st = _reconstruct(s, altitudes=s.altitudes + drift)
    placed = st.placed
    assert placed.sum() >= 0.75 * len(s)
    np.testing.assert_allclose(st.centres[placed, :2], s.centres[placed, :2], atol=0.5)
    lift = st.centres[placed, 2] - s.centres[placed, 2]
    assert np.median(lift) == pytest.approx(50.0, abs=5.0)
    assert np.ptp(lift) < 2.0  # level: under 2 degrees over the 54 x 36 m survey
    err = [st.points[i] - s.truth(i, st.observations[i]) for i in np.flatnonzero(placed)]
    horizontal = np.linalg.norm(np.concatenate(err)[:, :2], axis=1)
    assert np.percentile(horizontal, 95) < 2.0
    # the images it leaves out are those whose tags drifted furthest from the middle
    assert placed[2:-2].all()


def test_reconstruct_a_street_walk():
    """A walker's camera at 1.6 m looking 30 degrees off the way ahead at the facades: no
    ground plane, no camera looking down, the same path."""
    s = street(np.random.default_rng(1), n_points=2000)
    st = _reconstruct(s)
    _check_exact(s, st)
    assert np.abs(st.centres[:, 2] - s.centres[:, 2]).max() < 0.02  # 1.6 m above the road


def test_reconstruct_drops_a_camera_its_gps_puts_100_m_away():
    s = survey(np.random.default_rng(5))
    gps = s.positions.copy()
    gps[5, 0] += 100.0
    st = _reconstruct(s, positions=gps)
    assert st.placed.tolist() == [i != 5 for i in range(len(s))]
    assert np.isnan(st.centres[5]).all() and np.isnan(st.rotations[5]).all()
    assert len(st.observations[5]) == 0 and st.points[5].shape == (0, 3)
    keep = st.placed
    np.testing.assert_allclose(st.centres[keep], s.centres[keep], atol=0.05)


def test_reconstruct_two_areas_as_two_models():
    # two surveys 500 m apart share no point: two models, each aligned to its own tags
    a = survey(np.random.default_rng(6), rows=2, cols=3)
    b = survey(np.random.default_rng(7), rows=2, cols=3)
    off = np.array([500.0, 0.0, 0.0])
    both = Survey(np.concatenate([a.rotations, b.rotations]),
                  np.concatenate([a.centres, b.centres + off]), a.K,
                  np.concatenate([a.points, b.points + off]),
                  np.concatenate([a.descriptors, b.descriptors]),
                  a.keypoints + b.keypoints, a.image_descriptors + b.image_descriptors,
                  a.point_ids + [ids + len(a.points) for ids in b.point_ids])
    st = _reconstruct(both)
    assert st.models == 2 and st.placed.all()
    np.testing.assert_allclose(st.centres, both.centres, atol=0.02)
    assert _point_errors(both, st).max() < 0.1


def test_reconstruct_needs_three_related_images():
    # (unrelated images give no verified pair: test_build_geometry)
    s = survey(np.random.default_rng(8), rows=1, cols=4)
    pairs = exact_pairs(s)
    assert reconstruct(s.keypoints, [], s.positions, s.altitudes, F_TRUE) is None
    # two images: one pair, no model of three
    two = [p for p in pairs if (p.a, p.b) == (0, 1)]
    assert reconstruct(s.keypoints[:2], two, s.positions[:2], s.altitudes[:2], F_TRUE) is None
    assert reconstruct(s.keypoints, two, s.positions, s.altitudes, F_TRUE) is None
    # the same pairs, matched right, reconstruct
    assert reconstruct(s.keypoints, pairs, s.positions, s.altitudes, F_TRUE) is not None


def test_a_run_that_finds_no_model_writes_nothing_to_stderr(capfd):
    """COLMAP reports a mapper run without a model as an error on the process's stderr; the
    build handles that outcome (it reports no geometry), so a user's terminal and the
    service's log are not told of a fault."""
    s = survey(np.random.default_rng(8), rows=1, cols=4)
    # too few matches a pair for COLMAP to start a model from
    thin = [replace(p, matches=p.matches[:20]) for p in exact_pairs(s)]
    assert reconstruct(s.keypoints, thin, s.positions, s.altitudes, F_TRUE) is None
    assert capfd.readouterr().err == ""


def test_reconstruct_places_images_the_alignment_left_out_as_a_model_of_their_own():
    """The last two rows' tags lie 200 m east of where the images are (the mapper attaching
    a turn's banked images far from where they are, seen from the tags' side): the
    alignment of the whole keeps the first three rows, and the last two, reconstructed on
    their own, come back aligned to their own tags."""
    s = survey(np.random.default_rng(9), rows=5, cols=4)
    away = np.arange(len(s)) >= 12
    gps = s.positions.copy()
    gps[away, 0] += 200.0
    st = _reconstruct(s, positions=gps)
    assert st.placed.all() and st.models == 2
    np.testing.assert_allclose(st.centres[~away], s.centres[~away], atol=0.05)
    np.testing.assert_allclose(st.centres[away, :2], gps[away], atol=0.05)
    shifted = [st.points[i] - s.truth(i, st.observations[i]) for i in np.flatnonzero(away)]
    assert np.abs(np.concatenate(shifted) - [200.0, 0.0, 0.0]).max() < 0.1


def _pairs(*edges):
    return [PairMatches(a, b, np.zeros((15, 2), np.int64), 3) for a, b in edges]


def test_tied_groups_are_the_pair_graphs_components_among_the_images_asked():
    pairs = _pairs((0, 1), (1, 2), (2, 9), (3, 4), (5, 6), (6, 7), (7, 5), (8, 9), (4, 10))
    among = np.ones(11, bool)
    among[9] = False  # placed: its pairs tie nothing here, so 8 stands alone
    groups = tied_groups(pairs, among)
    assert [g.tolist() for g in groups] == [[0, 1, 2], [3, 4, 10], [5, 6, 7]]
    assert [g.tolist() for g in tied_groups(pairs, among, least=2)] == [
        [0, 1, 2], [3, 4, 10], [5, 6, 7]]
    assert [g.tolist() for g in tied_groups(pairs, np.ones(11, bool))] == [
        [0, 1, 2, 8, 9], [3, 4, 10], [5, 6, 7]]
    assert tied_groups(pairs, np.zeros(11, bool)) == []


def test_left_out_images_are_reconstructed_group_by_group_and_a_known_group_is_taken_up(
        monkeypatch):
    """Two groups of images that no tile placed, far apart: each is a reconstruction of its
    own with its own key, so that a build that finds one of them reconstructed already (an
    update that changed only the other) reconstructs only the other."""
    s = survey(np.random.default_rng(11), rows=2, cols=6)
    gps = tags(s.positions, s.altitudes)
    west, east = [0, 1, 10, 11], [4, 5, 6, 7]
    pairs = [p for p in exact_pairs(s)
             if {p.a, p.b} <= set(west) or {p.a, p.b} <= set(east)]
    assert [g.tolist() for g in tied_groups(pairs, np.ones(12, bool))] == [west, east]
    ran = []
    real = tiling.tile_models

    def spy(keypoints, pairs, gps, focal_px, inside, **kw):
        ran.append(sorted(np.asarray(inside).tolist()))
        return real(keypoints, pairs, gps, focal_px, inside, **kw)

    monkeypatch.setattr(tiling, "tile_models", spy)
    keys: list[str] = []
    models = left_out_models(s.keypoints, pairs, gps, F_TRUE, [], keys=keys)
    assert ran == [west, east] and len(keys) == 2 and keys[0] != keys[1]
    by_group = {tuple(sorted(m.images.tolist())): m for m in models}
    assert set(by_group) == {tuple(west), tuple(east)}
    for m in by_group.values():
        np.testing.assert_allclose(m.centres, s.centres[m.images], atol=0.05)
    # the west group known (reconstructed before, its inputs the same): only the east runs
    ran.clear()
    again = left_out_models(s.keypoints, pairs, gps, F_TRUE, [],
                            known_tiles={keys[0]: [by_group[tuple(west)]]})
    assert ran == [east]
    assert sorted(tuple(sorted(m.images.tolist())) for m in again) == [tuple(west), tuple(east)]


def test_left_out_models_need_three_tied_images_none_of_the_models_place():
    s = survey(np.random.default_rng(10), rows=2, cols=3)
    pairs = exact_pairs(s)
    gps = tags(s.positions, s.altitudes)
    first = tile_models(s.keypoints, pairs, gps, F_TRUE, np.arange(4))
    assert left_out_models(s.keypoints, pairs, gps, F_TRUE, first) == []
    rest = left_out_models(s.keypoints, pairs, gps, F_TRUE, first[:0])
    assert sorted(np.concatenate([m.images for m in rest]).tolist()) == list(range(6))
