"""Place descriptors end to end on arrays: registry, map assembly, query frames, packing."""

from __future__ import annotations

import numpy as np
import pytest

from tests.core.scenes import discs
from vloc.workers.core.features import ALL_FEATURE_NAMES, DESCRIPTOR_NAMES, FEATURE_NAMES
from vloc.workers.core.features.descriptors import (
    DESCRIPTORS,
    describe,
    get_descriptor,
    local_vectors,
)
from vloc.workers.core.geo import GeoOrigin
from vloc.workers.core.image import prepare
from vloc.workers.core.mapbuild import ImageFeatures, assemble_map, extract_image_features
from vloc.workers.core.mapdata import MapData
from vloc.workers.core.query import QueryFrame

ORIGIN = GeoOrigin(48.52, 9.05, 300.0)


@pytest.fixture(scope="module")
def frames():
    return [prepare(discs(s)) for s in range(6)]


@pytest.fixture(scope="module")
def feats(frames):
    return [extract_image_features(f) for f in frames]


def _assemble(feats, **kw) -> MapData:
    east = 10.0 * np.arange(len(feats))
    lat, lon = ORIGIN.to_wgs84(east, np.zeros_like(east))
    return assemble_map(names=[f"m{i}" for i in range(len(feats))], lats=lat, lons=lon,
                        alts=[0.0] * len(feats), features=feats, origin=ORIGIN, **kw)


@pytest.fixture(scope="module")
def place_map(feats):
    return _assemble(feats)


def test_registry():
    assert DESCRIPTOR_NAMES == ("vlad_orb", "vlad_rootsift", "bow_orb", "bow_rootsift")
    assert ALL_FEATURE_NAMES == FEATURE_NAMES + DESCRIPTOR_NAMES
    assert [DESCRIPTORS[n].dim for n in DESCRIPTOR_NAMES] == [2048, 4096, 4096, 4096]
    assert get_descriptor("bow_orb").binary and not get_descriptor("vlad_orb").binary
    with pytest.raises(ValueError, match="vlad_orb"):
        get_descriptor("netvlad")
    with pytest.raises(ValueError, match="ORB"):
        local_vectors("orb", sift=None)


def test_map_carries_a_vocabulary_and_a_matrix_per_descriptor(place_map):
    assert set(place_map.vocabularies) == set(DESCRIPTOR_NAMES)
    for name in DESCRIPTOR_NAMES:
        m = place_map.global_features[name]
        assert m.shape == (len(place_map), DESCRIPTORS[name].dim) and m.dtype == np.float32
        np.testing.assert_allclose(np.linalg.norm(m, axis=1), 1.0, rtol=1e-5)
    assert (place_map.global_features["vlad_orb"] < 0).any()
    assert (place_map.global_features["bow_orb"] >= 0).all()


def test_map_rows_are_the_descriptors_of_the_map_images(feats, place_map):
    for name in DESCRIPTOR_NAMES:
        spec = DESCRIPTORS[name]
        for i in (0, 4):
            v = local_vectors(spec.local, orb=feats[i].orb, sift=feats[i].sift)
            np.testing.assert_array_equal(place_map.global_features[name][i],
                                          describe(spec, v, place_map.vocabularies[name]))


def test_assembly_is_deterministic_under_the_seed(feats, place_map):
    again = _assemble(feats)
    other = _assemble(feats, seed=5)
    for name in DESCRIPTOR_NAMES:
        np.testing.assert_array_equal(again.vocabularies[name].centroids,
                                      place_map.vocabularies[name].centroids)
        np.testing.assert_array_equal(again.global_features[name],
                                      place_map.global_features[name])
    assert not np.array_equal(other.vocabularies["vlad_orb"].centroids,
                              place_map.vocabularies["vlad_orb"].centroids)


def test_images_without_orb_leave_the_orb_descriptors_out(feats):
    no_orb = [ImageFeatures(f.global_features, f.sift) for f in feats]
    m = _assemble(no_orb)
    assert set(m.vocabularies) == {"vlad_rootsift", "bow_rootsift"}
    assert "vlad_orb" not in m.global_features
    assert set(_assemble(feats, descriptors=()).vocabularies) == set()


def test_a_map_image_queried_is_its_own_best_match(frames, place_map):
    from vloc.workers.core.measures import descriptor_similarities

    q = QueryFrame(frames[3])
    got, ms = q.global_features(DESCRIPTOR_NAMES + ("wgoh",), place_map.vocabularies)
    assert list(got) == [*DESCRIPTOR_NAMES, "wgoh"] and ms > 0
    for name in DESCRIPTOR_NAMES:
        np.testing.assert_array_equal(got[name], place_map.global_features[name][3])
        s = descriptor_similarities(got[name], place_map.global_features[name])
        assert int(np.argmax(s)) == 3 and s[3] == pytest.approx(1.0, abs=1e-5)


def test_query_frame_needs_the_vocabulary(frames, place_map):
    q = QueryFrame(frames[0])
    with pytest.raises(ValueError, match="vocabulary"):
        q.global_features(("vlad_orb",))
    # a second map's vocabulary gives that map's descriptor, not the cached one
    other = _assemble([extract_image_features(f) for f in frames[::-1]], seed=3)
    a = q.global_features(("vlad_orb",), place_map.vocabularies)[0]["vlad_orb"]
    b = q.global_features(("vlad_orb",), other.vocabularies)[0]["vlad_orb"]
    assert not np.array_equal(a, b)
    np.testing.assert_array_equal(b, other.global_features["vlad_orb"][-1])


def test_packed_map_round_trip_and_old_maps_load(tmp_path, place_map):
    import json
    import shutil

    folder = place_map.save(tmp_path / "map")
    back = MapData.load(folder, mmap=True)
    for name in DESCRIPTOR_NAMES:
        a, b = place_map.vocabularies[name], back.vocabularies[name]
        assert (a.branching, a.depth, a.binary) == (b.branching, b.depth, b.binary)
        np.testing.assert_array_equal(a.centroids, b.centroids)
        np.testing.assert_array_equal(a.idf, b.idf)
        assert (a.projection is None) == (b.projection is None) == (name.startswith("bow"))
        if a.projection is not None:
            np.testing.assert_array_equal(a.projection, b.projection)
    # a folder packed before place descriptors: no vocabulary files, no meta key
    old = tmp_path / "old"
    shutil.copytree(folder, old)
    meta = json.loads((old / "meta.json").read_text())
    del meta["vocabularies"]
    meta["features"] = [n for n in meta["features"] if n not in DESCRIPTOR_NAMES]
    (old / "meta.json").write_text(json.dumps(meta))
    for f in old.glob("vocab_*.npy"):
        f.unlink()
    legacy = MapData.load(old)
    assert legacy.vocabularies == {} and "wgoh" in legacy.global_features


def test_a_vocabulary_needs_its_matrix(place_map):
    from dataclasses import replace

    with pytest.raises(ValueError, match="descriptor matrix"):
        replace(place_map, global_features={"wgoh": place_map.global_features["wgoh"]})
