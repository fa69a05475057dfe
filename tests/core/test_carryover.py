"""An update packed from the revision before: what it keeps, against a fresh packing."""

from __future__ import annotations

import numpy as np
import pytest

from tests.core import scenes
from tests.core.packing import assert_same_places
from vloc.workers.core import carryover, mapbuild
from vloc.workers.core.carryover import Previous, known_masks, merge_rows
from vloc.workers.core.features import DESCRIPTOR_NAMES
from vloc.workers.core.features.descriptors import describe, get_descriptor, local_vectors
from vloc.workers.core.features.distortion import image_distortion
from vloc.workers.core.geo import GeoOrigin
from vloc.workers.core.image import prepare
from vloc.workers.core.mapbuild import assemble_map, extract_image_features
from vloc.workers.core.mapdata import MapData
from vloc.workers.core.sift import reduction_masks, reduction_neighbours

ORIGIN = GeoOrigin(48.52, 9.05, 300.0)


@pytest.fixture(scope="module")
def discs():
    return [extract_image_features(prepare(scenes.discs(s))) for s in range(13)]


@pytest.fixture(scope="module")
def lines():
    return [extract_image_features(prepare(scenes.strokes(s))) for s in range(2)]


def _pack(feats, east, names, *, previous=None, revision=1, **kw) -> MapData:
    lat, lon = ORIGIN.to_wgs84(np.asarray(east, float), np.zeros(len(feats)))
    return assemble_map(names=names, lats=lat, lons=lon, alts=[0.0] * len(feats),
                        features=feats, origin=ORIGIN, geometry=False, previous=previous,
                        revision=revision, **kw)


@pytest.fixture(scope="module")
def first(discs, tmp_path_factory):
    """Ten images 10 m apart, packed and read back as a service's revision is."""
    data = _pack(discs[:10], 10.0 * np.arange(10), [f"d{i}" for i in range(10)])
    folder = tmp_path_factory.mktemp("rev") / "rev-000001"
    data.save(folder)
    return MapData.load(folder)


def _update(first, feats, east, names):
    previous = Previous.of(first, first.names, names)
    return (previous, _pack(feats, east, names, previous=previous, revision=2),
            _pack(feats, east, names, revision=2))


def test_the_fits_are_the_images_distortions_and_survive_the_folder(first, discs):
    for name in DESCRIPTOR_NAMES:
        fit, vocab = first.vocabulary_fits[name], first.vocabularies[name]
        local = get_descriptor(name).local
        expected = [image_distortion(vocab, local_vectors(local, orb=f.orb, sift=f.sift))
                    for f in discs[:10]]
        np.testing.assert_allclose(fit.images, expected, rtol=1e-6)
        assert fit.trained == pytest.approx(np.mean(expected), rel=1e-6)
        assert fit.revision == 1 and abs(fit.rise()) < 1e-6


ALIKE_EAST = np.r_[10.0 * np.arange(10), 5.0, 100.0]
"""Two more images, one between the first two (it becomes their nearest neighbour)."""


@pytest.fixture(scope="module")
def alike(first, discs):
    return _update(first, discs[:12], ALIKE_EAST, [*first.names, "d10", "d11"])


def test_images_like_the_map_keep_its_vocabularies_and_descriptors(first, discs, alike):
    feats = discs[:12]
    previous, updated, fresh = alike
    np.testing.assert_array_equal(previous.rows, np.r_[0:10, -1, -1])
    for name in DESCRIPTOR_NAMES:
        vocab, fit = updated.vocabularies[name], updated.vocabulary_fits[name]
        np.testing.assert_array_equal(vocab.centroids, first.vocabularies[name].centroids)
        np.testing.assert_array_equal(vocab.idf, first.vocabularies[name].idf)
        assert fit.revision == 1 and fit.trained == first.vocabulary_fits[name].trained
        assert 0.0 < fit.rise() <= carryover.MAX_DISTORTION_RISE
        matrix = updated.global_features[name]
        np.testing.assert_array_equal(matrix[:10], first.global_features[name])
        spec = get_descriptor(name)
        for i in (10, 11):
            np.testing.assert_array_equal(matrix[i], describe(
                spec, local_vectors(spec.local, orb=feats[i].orb, sift=feats[i].sift), vocab))
        # a fresh packing trains its own
        assert not np.array_equal(fresh.vocabularies[name].centroids, vocab.centroids)
    # the masks are a fresh packing's, those of images whose neighbours stayed taken over
    np.testing.assert_array_equal(updated.sift_keep, fresh.sift_keep)


def test_a_map_grown_by_more_than_a_fifth_since_training_trains_again(first, discs,
                                                                      alike, tmp_path):
    # 2 of 12 images untrained: kept, and the fit says which; read back from the folder
    _, updated, _ = alike
    fit = updated.vocabulary_fits["bow_orb"]
    assert fit.revision == 1 and fit.untrained_share() == pytest.approx(2 / 12)
    np.testing.assert_array_equal(fit.trained_on, [True] * 10 + [False] * 2)
    updated.save(tmp_path / "rev-000002")
    second = MapData.load(tmp_path / "rev-000002")
    np.testing.assert_array_equal(second.vocabulary_fits["bow_orb"].trained_on,
                                  fit.trained_on)
    # one more: 3 of 13 were not trained on, past a fifth however well they fit
    names = [*second.names, "d12"]
    east = np.r_[ALIKE_EAST, 110.0]
    third = _pack(discs[:13], east, names,
                  previous=Previous.of(second, second.names, names), revision=3)
    fresh = _pack(discs[:13], east, names, revision=3)
    for name in DESCRIPTOR_NAMES:
        assert third.vocabulary_fits[name].revision == 3
        assert third.vocabulary_fits[name].untrained_share() == 0.0
        np.testing.assert_array_equal(third.global_features[name],
                                      fresh.global_features[name])


def test_images_unlike_the_map_train_its_vocabularies_again(first, discs, lines):
    # two images of twelve, as few as the alike ones that keep the vocabularies
    feats = discs[:10] + lines
    east = np.r_[10.0 * np.arange(10), 100.0, 110.0]
    names = [*first.names, "l0", "l1"]
    _, updated, fresh = _update(first, feats, east, names)
    assert {f.revision for f in updated.vocabulary_fits.values()} == {2}
    assert_same_places(updated, fresh)
    # the strokes would have raised at least one vocabulary's distortion past the bound
    rises = []
    for name in DESCRIPTOR_NAMES:
        vocab, fit = first.vocabularies[name], first.vocabulary_fits[name]
        local = get_descriptor(name).local
        added = [image_distortion(vocab, local_vectors(local, orb=f.orb, sift=f.sift))
                 for f in lines]
        rises.append(np.mean(np.r_[fit.images, added]) / fit.trained - 1.0)
    assert max(rises) > carryover.MAX_DISTORTION_RISE


def test_a_deletion_keeps_the_other_images_rows(first, discs):
    keep = [0, 1, 2, 4, 5, 6, 7, 8, 9]
    feats = [discs[i] for i in keep]
    names = [first.names[i] for i in keep]
    previous = Previous.of(first, first.names, names)
    updated = _pack(feats, 10.0 * np.asarray(keep), names, previous=previous, revision=2)
    assert previous.added.size == 0
    for name in DESCRIPTOR_NAMES:
        assert updated.vocabulary_fits[name].revision == 1
        np.testing.assert_array_equal(updated.global_features[name],
                                      first.global_features[name][keep])
        np.testing.assert_array_equal(updated.vocabulary_fits[name].images,
                                      first.vocabulary_fits[name].images[keep])
    # image 1's and 2's neighbours changed with the deletion, the others' did not: all
    # are the masks a fresh reduction gives
    fresh = reduction_masks([f.sift for f in feats], np.asarray(updated.positions))
    np.testing.assert_array_equal(updated.sift_keep, np.concatenate(fresh))


def test_a_revision_without_fits_is_not_carried_over(first, discs, alike):
    # a revision packed before fits were recorded: packed afresh
    bare = MapData(**{f: getattr(first, f) for f in (
        "origin", "names", "positions", "altitudes", "global_features", "sift_offsets",
        "sift_keypoints", "sift_descriptors", "sift_keep", "vocabularies", "orb_offsets",
        "orb_keypoints", "orb_descriptors")})
    names = [*first.names, "d10", "d11"]
    updated = _pack(discs[:12], ALIKE_EAST, names,
                    previous=Previous.of(bare, bare.names, names), revision=2)
    fresh = alike[2]
    for name in DESCRIPTOR_NAMES:
        assert updated.vocabulary_fits[name].revision == 2
        np.testing.assert_array_equal(updated.global_features[name],
                                      fresh.global_features[name])


def test_shortlist_codes_are_carried_in_their_basis(first, discs, monkeypatch):
    # a map of more than five images keeps codes (their basis: the principal directions
    # of its 2048-dimensional descriptors)
    monkeypatch.setattr(mapbuild, "CODES_FROM", 5)
    one = ("vlad_orb",)
    coded = _pack(discs[:10], 10.0 * np.arange(10), list(first.names), descriptors=one)
    feats, names = discs[:11], [*first.names, "d10"]
    previous = Previous.of(coded, coded.names, names)
    updated = _pack(feats, np.r_[10.0 * np.arange(10), 100.0], names, previous=previous,
                    revision=2, descriptors=one)
    assert updated.vocabulary_fits["vlad_orb"].revision == 1
    for name in one:
        before, after = coded.place_codes[name], updated.place_codes[name]
        np.testing.assert_array_equal(after.basis, before.basis)
        np.testing.assert_array_equal(after.codes[:10], before.codes)
        np.testing.assert_allclose(after.codes[10],
                                   updated.global_features[name][10] @ before.basis,
                                   rtol=1e-5, atol=1e-6)


def test_known_masks_are_taken_only_where_the_neighbours_stayed(discs):
    sift = [f.sift for f in discs[:4]]
    east = np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 0.0], [30.0, 0.0]])
    fresh = reduction_masks(sift, east)
    near = reduction_neighbours(east)
    assert near[0] == frozenset({1, 2}) and near[3] == frozenset({1, 2})
    wrong = [~m for m in fresh]
    # image 0's recorded neighbours are its nearest now: its (deliberately wrong) mask is
    # taken as it is; image 3's are not: matched again
    masks = reduction_masks(sift, east, known={0: (near[0], wrong[0]),
                                               3: (frozenset({0, 1}), wrong[3])})
    np.testing.assert_array_equal(masks[0], wrong[0])
    np.testing.assert_array_equal(masks[3], fresh[3])
    # a mask of another length (the image's features extracted again) is not taken
    masks = reduction_masks(sift, east, known={0: (near[0], wrong[0][:-1])})
    np.testing.assert_array_equal(masks[0], fresh[0])


def test_known_masks_follow_the_images_and_skip_deleted_neighbours(first):
    # the first revision's images 1..9, image 0 deleted
    previous = Previous.of(first, first.names, first.names[1:])
    known = known_masks(previous)
    # the image whose recorded neighbours include the deleted one has no known mask
    assert 0 not in known and set(known) == set(range(1, 9))
    offsets = np.asarray(first.sift_offsets)
    for i, (near, mask) in known.items():
        np.testing.assert_array_equal(mask, first.sift_keep[offsets[i + 1]:offsets[i + 2]])
        assert near == frozenset(j - 1 for j in reduction_neighbours(
            np.asarray(first.positions))[i + 1])


def test_merge_rows_puts_each_row_in_its_place(first):
    out = merge_rows(np.array([0, 2, 3]), np.array([[1.0], [3.0], [4.0]]), np.array([[2.0]]))
    np.testing.assert_array_equal(out, [[1.0], [2.0], [3.0], [4.0]])
    with pytest.raises(ValueError, match="identities"):
        Previous.of(first, first.names[:3], first.names)
