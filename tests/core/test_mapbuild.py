"""map_geometry: the map cameras and every stored keypoint's 3-D point, at map build."""

from __future__ import annotations

import contextlib
import errno
import os
import resource

import numpy as np
import pytest

from tests.core.geometry.scene import F_TRUE, survey
from vloc.workers.core.carryover import Previous
from vloc.workers.core.geo import GeoOrigin
from vloc.workers.core.image import prepare
from vloc.workers.core.mapbuild import (
    ImageFeatures,
    assemble_map,
    extract_image_features,
    map_geometry,
)
from vloc.workers.core.mapdata import MapData
from vloc.workers.core.sift import SiftFeatures
from vloc.workers.core.tiepoints import (
    TiePointFiles,
    load_tie_points,
    save_tie_points,
)
from vloc.workers.core.timings import top_level

ORIGIN = GeoOrigin(41.03, -83.30, 260.0)


def _survey_map(seed: int = 0):
    s = survey(np.random.default_rng(seed), max_tilt_deg=8.0)
    data = MapData.from_parts(origin=ORIGIN, names=[f"m{i}" for i in range(len(s.centres))],
                              positions=s.positions, altitudes=s.altitudes, global_features={},
                              sift=[SiftFeatures(k, d) for k, d in
                                    zip(s.keypoints, s.image_descriptors, strict=True)])
    return s, data


@pytest.mark.parametrize("focal_px", [F_TRUE, None], ids=["exif", "assumed"])
def test_map_geometry_gives_every_keypoint_its_3d_point(focal_px):
    # None assumes a 65 degree lens (251 px) where the truth is 60 degrees (277 px): the
    # hills and buildings under the survey tell the reconstruction
    s, data = _survey_map()
    geo = map_geometry(data, focal_px=focal_px)
    assert geo is not None and geo.reconstructed.all()
    assert geo.intrinsics.f == pytest.approx(F_TRUE, rel=1e-3)
    points = np.asarray(geo.points["sift"])
    assert points.shape == (len(data.sift_keypoints), 3) and points.dtype == np.float32
    truth = s.points[np.concatenate(s.point_ids)]
    err = np.linalg.norm(points - truth, axis=1)
    # keypoints no other image sees have no reconstructed tie point near them
    assert np.isfinite(err).mean() > 0.8
    assert np.nanmedian(err) < 0.5
    # the map localised its own images before its geometry was trusted
    check = geo.self_check
    assert check["trusted"] and check["images"] == len(s.centres)
    assert check["median_m"] < 1.0 < check["floor_median_m"]


def test_map_geometry_of_unrelated_textures_is_none():
    rng = np.random.default_rng(4)
    frames = [prepare(rng.integers(0, 256, (60, 80, 3), dtype=np.uint8).repeat(4, 0).repeat(4, 1))
              for _ in range(4)]
    lat, lon = ORIGIN.to_wgs84(np.array([0.0, 10.0, 20.0, 30.0]), np.zeros(4))
    data = assemble_map(names=list("abcd"), lats=lat, lons=lon, alts=[300.0] * 4,
                        features=[extract_image_features(f, features=()) for f in frames],
                        origin=ORIGIN)
    assert min(data.sift_counts()) > 50  # there are features, they just do not agree
    assert data.geometry is None
    assert map_geometry(data) is None


def test_assemble_map_without_geometry():
    s, data = _survey_map(1)
    feats = [ImageFeatures({}, SiftFeatures(k, d))
             for k, d in zip(s.keypoints, s.image_descriptors, strict=True)]
    lat, lon = ORIGIN.to_wgs84(s.positions[:, 0], s.positions[:, 1])
    kwargs = dict(names=data.names, lats=lat, lons=lon, alts=list(s.altitudes),
                  features=feats, origin=ORIGIN, focal_px=F_TRUE)
    assert assemble_map(**kwargs, geometry=False).geometry is None
    built = assemble_map(**kwargs)
    assert built.geometry is not None and sorted(built.geometry.points) == ["sift"]


def test_assemble_map_reports_the_seconds_of_each_stage():
    s, data = _survey_map(2)
    feats = [ImageFeatures({}, SiftFeatures(k, d))
             for k, d in zip(s.keypoints, s.image_descriptors, strict=True)]
    lat, lon = ORIGIN.to_wgs84(s.positions[:, 0], s.positions[:, 1])
    timings: dict = {}
    assemble_map(names=data.names, lats=lat, lons=lon, alts=list(s.altitudes), features=feats,
                 origin=ORIGIN, focal_px=F_TRUE, timings=timings)
    parts = {"geometry: cameras", "geometry: cameras: left-out models",
             "geometry: 3-D points", "geometry: self-check"}
    assert set(timings) == {"sift reduction", "vocabularies", "packing", "geometry"} | parts
    assert set(top_level(timings)) == {"sift reduction", "vocabularies", "packing", "geometry"}
    for wall, cpu in timings.values():
        assert wall >= 0.0 and cpu >= 0.0
    # the parts are timed inside their stage: they add up to no more than it
    whole = timings["geometry"][0]
    assert timings["geometry: cameras: left-out models"][0] <= timings["geometry: cameras"][0]
    assert sum(timings[p][0] for p in parts - {"geometry: cameras: left-out models"}) <= whole
    timings.clear()
    assemble_map(names=data.names, lats=lat, lons=lon, alts=list(s.altitudes), features=feats,
                 origin=ORIGIN, focal_px=F_TRUE, geometry=False, timings=timings)
    assert "geometry" not in timings


def _stored(s, n=80):
    """The SIFT a map stores of each image: ``n`` of its keypoints, drawn at random; the
    survey's keypoints are its tie points."""
    rng = np.random.default_rng(0)
    rows = [np.sort(rng.choice(len(k), n, replace=False)) for k in s.keypoints]
    few = [SiftFeatures(k[r], d[r])
           for k, d, r in zip(s.keypoints, s.image_descriptors, rows, strict=True)]
    ties = [SiftFeatures(k, d) for k, d in zip(s.keypoints, s.image_descriptors, strict=True)]
    return few, ties, rows


def test_tie_points_reconstruct_a_map_its_stored_sift_cannot_tie():
    s, _ = _survey_map(3)
    # the stored SIFT: 80 keypoints an image, too few shared to verify a pair, enough to
    # localise an image against three neighbours together
    few, ties, rows = _stored(s)
    lat, lon = ORIGIN.to_wgs84(s.positions[:, 0], s.positions[:, 1])
    kwargs = dict(names=[f"m{i}" for i in range(len(few))], lats=lat, lons=lon,
                  alts=list(s.altitudes), origin=ORIGIN, focal_px=F_TRUE)
    bare = assemble_map(**kwargs, features=[ImageFeatures({}, f) for f in few])
    assert bare.geometry is None
    tied = assemble_map(**kwargs, features=[ImageFeatures({}, f, tie=t)
                                            for f, t in zip(few, ties, strict=True)])
    geo = tied.geometry
    assert geo is not None and geo.reconstructed.all() and geo.self_check["trusted"]
    # the stored keypoints (not the tie points) are the ones given 3-D points
    points = np.asarray(geo.points["sift"])
    assert points.shape == (80 * len(few), 3)
    truth = s.points[np.concatenate([ids[r] for ids, r in zip(s.point_ids, rows,
                                                                strict=True)])]
    assert np.nanmedian(np.linalg.norm(points - truth, axis=1)) < 0.5
    with pytest.raises(ValueError, match="tie points"):
        map_geometry(tied, tie_points=ties[:-1])


@contextlib.contextmanager
def _open_files_limited_to(extra: int):
    """This process may open ``extra`` more files than it has open now, until the block ends."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    resource.setrlimit(resource.RLIMIT_NOFILE, (len(os.listdir("/proc/self/fd")) + extra, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))


def test_tie_points_on_disk_tie_the_same_map_with_a_few_files_open(tmp_path):
    # A map of 50,000 images failed to pack with "Too many open files": every image's tie
    # points were mapped at once, and each mapped array holds a file descriptor.
    s, _ = _survey_map(3)
    few, ties, _ = _stored(s)
    for i, t in enumerate(ties):
        save_tie_points(t, tmp_path / str(i))
    lat, lon = ORIGIN.to_wgs84(s.positions[:, 0], s.positions[:, 1])
    kwargs = dict(names=[f"m{i}" for i in range(len(ties))], lats=lat, lons=lon,
                  alts=list(s.altitudes), origin=ORIGIN, focal_px=F_TRUE)
    in_memory = assemble_map(**kwargs, features=[ImageFeatures({}, f, tie=t)
                                                 for f, t in zip(few, ties, strict=True)])
    files = [TiePointFiles.find(tmp_path / str(i)) for i in range(len(ties))]
    assert TiePointFiles.find(tmp_path / "never-written") is None
    assert [len(f) for f in files] == [len(t) for t in ties]
    # two files an image: eight images mapped at once need sixteen
    with _open_files_limited_to(8):
        with pytest.raises(OSError) as held:
            [load_tie_points(tmp_path / str(i)) for i in range(len(ties))]
        assert held.value.errno == errno.EMFILE
        on_disk = assemble_map(**kwargs, features=[ImageFeatures({}, f, tie=t)
                                                   for f, t in zip(few, files, strict=True)])
    want, got = in_memory.geometry, on_disk.geometry
    assert want is not None and want.reconstructed.all()
    np.testing.assert_array_equal(got.centres, want.centres)
    np.testing.assert_array_equal(got.rotations, want.rotations)
    np.testing.assert_array_equal(got.points["sift"], want.points["sift"])
    assert got.self_check == want.self_check


def test_an_update_takes_up_the_points_of_the_images_whose_structure_stayed(tmp_path):
    """An image whose pose, reconstructed tie points and intrinsics are the revision
    before's (a large map's tile that no added image reached) keeps its keypoints' 3-D
    points from there; the others are worked out again."""
    _, data = _survey_map()
    names = list(data.names)
    data.geometry = map_geometry(data, focal_px=F_TRUE)
    first = data.geometry
    assert first.digests.shape == (len(data), 16) and first.digests.any(axis=1).all()
    data.save(tmp_path / "rev")
    before = MapData.load(tmp_path / "rev")
    np.testing.assert_array_equal(before.geometry.digests, first.digests)
    # mark the revision before's points, which no working-out gives, to see which are taken
    offsets = np.asarray(before.sift_offsets)
    marked = np.array(before.geometry.points["sift"])
    marked[:] = 42.0
    before.geometry.points["sift"] = marked
    digests = np.array(before.geometry.digests)
    digests[1, 0] ^= 1  # image 1's structure moved since
    before.geometry.digests = digests
    again = map_geometry(data, focal_px=F_TRUE, previous=Previous.of(before, names, names))
    np.testing.assert_array_equal(again.digests, first.digests)  # the same structure
    points = np.asarray(again.points["sift"])
    for i in range(len(data)):
        rows = slice(offsets[i], offsets[i + 1])
        if i == 1:
            np.testing.assert_array_equal(points[rows], np.asarray(first.points["sift"])[rows])
        else:
            assert (points[rows] == 42.0).all()
    # an image added is worked out again too
    previous = Previous.of(before, names, ["new", *names[1:]])
    again = map_geometry(data, focal_px=F_TRUE, previous=previous)
    rows0 = slice(offsets[0], offsets[1])
    np.testing.assert_array_equal(np.asarray(again.points["sift"])[rows0],
                                  np.asarray(first.points["sift"])[rows0])
    # a revision packed before digests were kept gives nothing
    before.geometry.digests = None
    again = map_geometry(data, focal_px=F_TRUE, previous=Previous.of(before, names, names))
    np.testing.assert_array_equal(again.points["sift"], first.points["sift"])
