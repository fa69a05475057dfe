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
    centres = np.array([[0.0, 0.0, 310.0], [10.0, 0.0, 311.0], [np.nan] * 3])
    geo = MapGeometry(rotations, centres, Intrinsics(250.0, 159.5, 119.5), k1=-0.01,
                      residual_px=0.4, gps_rms=0.8, gps_rms_v=2.5)
    # each keypoint of image 0 on a tie point 30 m below it (image 1 has none)
    offsets = np.asarray(data.sift_offsets)
    kp0 = np.asarray(data.sift_keypoints)[offsets[0]:offsets[1], :2].astype(np.float64)
    xyz = centres[0] + (30.0 * geo.rays(kp0)) @ rotations[0]
    nothing = (np.zeros((0, 2)), np.zeros((0, 3)))
    geo.add_points("sift", np.asarray(data.sift_keypoints), offsets,
                   [(kp0, xyz), nothing, nothing])
    geo.self_check = {"images": 2, "registered": 1.0, "median_m": 0.7, "sigma_m": 2.0,
                      "trusted": True}
    return geo


@pytest.mark.parametrize("mmap", [True, False])
def test_save_load_keeps_geometry(tmp_path, mmap):
    data = _map(np.random.default_rng(0))
    data.geometry = _geometry(data)
    back = MapData.load(data.save(tmp_path / "map"), mmap=mmap)
    geo = back.geometry
    assert geo is not None
    assert all(isinstance(part, np.memmap) is mmap for part in geo.points["sift"].parts)
    np.testing.assert_array_equal(geo.rotations, data.geometry.rotations)
    np.testing.assert_array_equal(geo.centres, data.geometry.centres)
    assert geo.intrinsics == Intrinsics(250.0, 159.5, 119.5)
    assert (geo.k1, geo.residual_px, geo.gps_rms, geo.gps_rms_v) == (-0.01, 0.4, 0.8, 2.5)
    assert geo.self_check == data.geometry.self_check
    # the 3-D points stay row-aligned with the keypoints: image 0's five 30 m below its
    # camera, image 2's (no camera) unknown
    points = np.asarray(geo.points["sift"])
    assert points.shape == (len(back.sift_keypoints), 3)
    np.testing.assert_array_equal(points, data.geometry.points["sift"])
    np.testing.assert_allclose(points[:5, 2], 280.0, atol=1e-3)
    assert np.isnan(points[5:]).all()
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
    # each set's keypoints and offsets, by the name its geometry's points go by
    kps, offsets = back.keypoint_set("orb")
    np.testing.assert_array_equal(offsets, [0, 4, 4, 10])
    np.testing.assert_array_equal(kps[4:10], orb[2].keypoints)
    np.testing.assert_array_equal(back.keypoint_set("sift")[1], back.sift_offsets)
    with pytest.raises(KeyError, match="orb"):
        base.keypoint_set("orb")


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


def _timed_map(positions: np.ndarray, times: np.ndarray) -> MapData:
    n = len(positions)
    empty = SiftFeatures(np.zeros((0, 4), np.float32), np.zeros((0, 128), np.uint8))
    return MapData.from_parts(origin=GeoOrigin(41.03, -83.3, 280.0),
                              names=[f"m{i}" for i in range(n)], positions=positions,
                              altitudes=np.full(n, 300.0),
                              global_features={"wgoh": np.zeros((n, 8))},
                              sift=[empty] * n, captured_at=times)


def _lawnmower(speed: float, lanes: int, per_lane: int, lane_gap: float, interval: float,
               rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A survey's frames: lanes flown back and forth at ``speed`` with gusts, one frame
    every ``interval`` seconds (jittered)."""
    step = speed * interval
    xs, ys = [], []
    for lane in range(lanes):
        along = step * np.arange(per_lane)
        xs.append(along if lane % 2 == 0 else along[::-1])
        ys.append(np.full(per_lane, lane * lane_gap))
    xy = np.column_stack([np.concatenate(xs), np.concatenate(ys)])
    xy += rng.normal(0.0, 0.3 * step, xy.shape)
    times = np.cumsum(rng.uniform(0.8, 1.2, len(xy)) * interval)
    return xy, times


def _time_ordered_speed(*flights: tuple[np.ndarray, np.ndarray]) -> float:
    """The obvious reference: the median speed between consecutive captures of each
    flight, ``flights`` given apart."""
    steps = []
    for xy, times in flights:
        order = np.argsort(times)
        steps.append((np.diff(times[order]),
                      np.linalg.norm(np.diff(xy[order], axis=0), axis=1)))
    dt, dist = (np.concatenate(part) for part in zip(*steps, strict=True))
    keep = dt <= 5.0 * np.median(dt)
    return float(np.median(dist[keep] / dt[keep]))


def test_speed_of_one_flight_is_that_between_consecutive_captures():
    rng = np.random.default_rng(3)
    xy, times = _lawnmower(6.0, lanes=5, per_lane=40, lane_gap=28.0, interval=1.0, rng=rng)
    data = _timed_map(xy, times)
    assert data.typical_speed() == pytest.approx(_time_ordered_speed((xy, times)), rel=1e-12)
    assert data.typical_speed() == pytest.approx(6.0, rel=0.1)
    assert data.typical_interval() == pytest.approx(np.median(np.diff(times)), rel=1e-12)


def test_speed_of_flights_flown_at_the_same_time_is_each_flights_own():
    # Four platforms survey four squares 600 m apart at once: the next capture in the
    # whole map is usually another platform's, hundreds of metres away.
    rng = np.random.default_rng(4)
    parts = [_lawnmower(6.0, lanes=4, per_lane=30, lane_gap=28.0, interval=1.0, rng=rng)
             for _ in range(4)]
    xy = np.concatenate([p[0] + [600.0 * k, 0.0] for k, p in enumerate(parts)])
    times = np.concatenate([p[1] for p in parts])
    data = _timed_map(xy, times)
    assert _time_ordered_speed((xy, times)) > 100.0  # consecutive captures of the whole map
    assert data.typical_speed() == pytest.approx(_time_ordered_speed(*parts), rel=1e-12)
    assert data.typical_speed() == pytest.approx(6.0, rel=0.15)
    assert data.typical_interval() == pytest.approx(1.0, rel=0.1)


def test_speed_needs_timed_captures():
    xy = np.column_stack([np.arange(5.0), np.zeros(5)])
    assert _timed_map(xy, np.full(5, np.nan)).typical_speed() is None
    times = np.array([0.0, np.nan, np.nan, np.nan, 1.0])
    assert _timed_map(xy, times).typical_speed() is None
    assert _timed_map(xy, times).typical_interval() is None


def test_flight_names_round_trip_and_maps_without_them_keep_their_format(tmp_path):
    import json

    base = _map(np.random.default_rng(4))
    parts = dict(origin=base.origin, names=base.names, positions=base.positions,
                 altitudes=base.altitudes, global_features=base.global_features,
                 sift=[base.sift(i) for i in range(3)], captured_at=[0.0, 10.0, 20.0])
    named = MapData.from_parts(**parts, flights=["dawn", None, "dusk"])
    back = MapData.load(named.save(tmp_path / "named"))
    assert back.flights == ("dawn", None, "dusk")
    assert back.flight_labels().tolist() == [0, 1, 2]  # the unnamed image flew between
    # no name given: no flights in the map, nor in its meta.json (as before names existed)
    for flights in (None, [None, None, None]):
        plain = MapData.from_parts(**parts, flights=flights)
        assert plain.flights is None
        folder = plain.save(tmp_path / "plain")
        assert "flights" not in json.loads((folder / "meta.json").read_text())
        assert MapData.load(folder).flights is None
    with pytest.raises(ValueError, match="flights must have 3 entries"):
        MapData.from_parts(**parts, flights=["a", "b"])
