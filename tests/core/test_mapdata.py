"""MapData persistence carries the map's camera geometry."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from vloc.workers.core.geo import GeoOrigin
from vloc.workers.core.geometry.camera import Intrinsics, nadir_rotation
from vloc.workers.core.geometry.mapgeometry import MapGeometry
from vloc.workers.core.mapdata import MapData
from vloc.workers.core.sift import SiftFeatures


def _map(rng: np.random.Generator) -> MapData:
    counts = [5, 0, 7]
    sift = [SiftFeatures(rng.uniform(0, 240, (k, 4)).astype(np.float32),
                         rng.integers(0, 256, (k, 128), dtype=np.uint8)) for k in counts]
    return MapData.from_parts(origin=GeoOrigin(41.03, -83.3, 280.0), names=["a", "b", "c"],
                              positions=[[0.0, 0.0], [10.0, 0.0], [20.0, 1.0]],
                              altitudes=[300.0, 301.0, np.nan],
                              global_features={"wgoh": rng.random((3, 8))}, sift=sift,
                              map_id="m", revision=2)


def _geometry(data: MapData) -> MapGeometry:
    rotations = np.stack([nadir_rotation(0.1), nadir_rotation(0.2), np.full((3, 3), np.nan)])
    centres = np.array([[0.0, 0.0, 30.0], [10.0, 0.0, 31.0], [np.nan] * 3])
    geo = MapGeometry(rotations, centres, Intrinsics(250.0, 160.0, 120.0), ground_alt=270.0,
                      residual_px=0.4, gps_rms=0.8)
    geo.add_ground("sift", np.asarray(data.sift_keypoints), np.asarray(data.sift_offsets))
    return geo


@pytest.mark.parametrize("mmap", [True, False])
def test_save_load_keeps_geometry(tmp_path, mmap):
    data = _map(np.random.default_rng(0))
    data.geometry = _geometry(data)
    back = MapData.load(data.save(tmp_path / "map"), mmap=mmap)
    geo = back.geometry
    assert geo is not None
    assert isinstance(geo.ground["sift"], np.memmap) is mmap
    np.testing.assert_array_equal(geo.rotations, data.geometry.rotations)
    np.testing.assert_array_equal(geo.centres, data.geometry.centres)
    assert geo.intrinsics == Intrinsics(250.0, 160.0, 120.0)
    assert (geo.ground_alt, geo.residual_px, geo.gps_rms) == (270.0, 0.4, 0.8)
    # the ground positions stay row-aligned with the keypoints
    ground = np.asarray(geo.ground["sift"])
    assert ground.shape == (len(back.sift_keypoints), 2)
    np.testing.assert_array_equal(ground, data.geometry.ground["sift"])
    assert np.isfinite(ground[:5]).all() and np.isnan(ground[5:]).all()
    assert back.names == data.names and back.revision == 2


def test_map_without_geometry_loads_with_none(tmp_path):
    data = _map(np.random.default_rng(1))
    assert MapData.load(data.save(tmp_path / "map")).geometry is None
    # ... also when it replaces a save that had one
    data.geometry = _geometry(data)
    data.save(tmp_path / "again")
    assert MapData.load(tmp_path / "again").geometry is not None
    data.geometry = None
    data.save(tmp_path / "again")
    assert MapData.load(tmp_path / "again").geometry is None
    assert not list((tmp_path / "again").glob("geometry*"))


def test_orb_features_round_trip(tmp_path):
    from vloc.workers.core.features.orb import OrbFeatures

    rng = np.random.default_rng(3)
    orb = [OrbFeatures(rng.uniform(0, 240, (k, 4)).astype(np.float32),
                       rng.integers(0, 256, (k, 32), dtype=np.uint8)) for k in (4, 0, 6)]
    base = _map(np.random.default_rng(0))
    data = MapData.from_parts(origin=base.origin, names=base.names, positions=base.positions,
                              altitudes=base.altitudes, global_features=base.global_features,
                              sift=[base.sift(i) for i in range(3)], orb=orb)
    assert data.has_orb and not base.has_orb
    np.testing.assert_array_equal(data.orb_offsets, [0, 4, 4, 10])
    back = MapData.load(data.save(tmp_path / "map"))
    for i in range(3):
        np.testing.assert_array_equal(back.orb(i).descriptors, orb[i].descriptors)
        np.testing.assert_array_equal(back.orb(i).keypoints, orb[i].keypoints)
    # a map packed without ORB loads without it
    assert not MapData.load(base.save(tmp_path / "plain")).has_orb


def test_reduced_sift_of_one_image_copies_only_that_image(tmp_path):
    # 400 images of 200 keypoints: the reduced set of image i is its own keypoints under
    # its own mask, and reading it allocates about one image's worth, not the map's.
    rng = np.random.default_rng(3)
    n, k = 400, 200
    sift = [SiftFeatures(rng.uniform(0, 240, (k, 4)).astype(np.float32),
                         rng.integers(0, 256, (k, 128), dtype=np.uint8)) for _ in range(n)]
    keep = [rng.random(k) < 0.6 for _ in range(n)]
    data = MapData.from_parts(origin=GeoOrigin(41.03, -83.3, 280.0),
                              names=[f"m{i}" for i in range(n)],
                              positions=np.column_stack([np.arange(n) * 5.0, np.zeros(n)]),
                              altitudes=np.full(n, 300.0), global_features={}, sift=sift,
                              sift_keep=keep)
    back = MapData.load(data.save(tmp_path / "map"), mmap=True)
    tracemalloc.start()
    try:
        for i in (0, 17, n - 1):
            reduced = back.sift(i, reduced=True)
            np.testing.assert_array_equal(reduced.keypoints, sift[i].keypoints[keep[i]])
            np.testing.assert_array_equal(reduced.descriptors, sift[i].descriptors[keep[i]])
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    whole = n * k * (128 + 16)
    assert peak < whole / 20
    np.testing.assert_array_equal(back.sift(5).descriptors, sift[5].descriptors)
