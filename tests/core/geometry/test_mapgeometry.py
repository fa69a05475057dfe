"""A map's camera geometry: keypoints on the ground, persistence beside the map."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.core.geometry.scene import tilted_rotation
from vloc.workers.core.geometry.camera import Intrinsics, nadir_rotation, project
from vloc.workers.core.geometry.mapgeometry import MapGeometry
from vloc.workers.core.geometry.reconstruct import PlaneReconstruction

K = Intrinsics(100.0, 160.0, 120.0)


def _geometry() -> MapGeometry:
    """Three map images: a nadir camera, one not reconstructed, a tilted one."""
    rotations = np.stack([nadir_rotation(0.0), np.full((3, 3), np.nan),
                          tilted_rotation(2.0, 8.0, 1.0)])
    centres = np.array([[10.0, 20.0, 50.0], [np.nan] * 3, [-30.0, 5.0, 35.0]])
    return MapGeometry(rotations, centres, K, ground_alt=180.5, residual_px=0.7, gps_rms=1.2)


def test_add_ground_places_keypoints_of_known_cameras():
    geo = _geometry()
    kp0 = np.array([[160, 120, 3, 0], [260, 120, 3, 0], [160, 220, 3, 0], [110, 70, 3, 0]],
                   np.float32)
    kp1 = np.array([[100, 100, 3, 0], [200, 50, 3, 0]], np.float32)
    truth2 = np.array([[-30.0, 5.0], [-25.0, 12.0], [-41.0, -3.5]])
    kp2 = np.zeros((3, 4), np.float32)
    kp2[:, :2] = project(geo.rotations[2], geo.centres[2], K,
                         np.column_stack([truth2, np.zeros(3)]))
    keypoints = np.concatenate([kp0, kp1, kp2])
    offsets = np.array([0, 4, 6, 9])
    geo.add_ground("sift", keypoints, offsets)
    ground = geo.ground["sift"]
    assert ground.dtype == np.float32 and ground.shape == (9, 2)
    # nadir, heading 0, 50 m up, f = 100: a focal length off centre is 50 m on the ground
    np.testing.assert_allclose(ground[:4], [[10, 20], [60, 20], [10, -30], [-15, 45]],
                               atol=1e-4)
    assert np.isnan(ground[4:6]).all()  # image 1 has no camera
    np.testing.assert_allclose(ground[6:], truth2, atol=1e-3)


def test_add_ground_with_an_image_without_keypoints():
    geo = _geometry()
    keypoints = np.array([[160, 120, 1, 0], [200, 100, 1, 0]], np.float32)
    geo.add_ground("sift", keypoints, np.array([0, 2, 2, 2]))
    np.testing.assert_allclose(geo.ground["sift"][0], [10, 20], atol=1e-5)
    assert np.isfinite(geo.ground["sift"]).all()


def test_reconstructed_and_height_range():
    geo = _geometry()
    assert geo.reconstructed.tolist() == [True, False, True]
    assert geo.height_range() == pytest.approx((0.5 * 35.0, 1.6 * 50.0))
    none = MapGeometry(np.full((2, 3, 3), np.nan), np.full((2, 3), np.nan), K, 0.0, 0.0, 0.0)
    assert none.height_range() == (0.0, 0.0)


def test_from_reconstruction_carries_every_field():
    geo = _geometry()
    rec = PlaneReconstruction(geo.rotations, geo.centres, K, 180.5, 0.7, 1.2)
    out = MapGeometry.from_reconstruction(rec)
    assert out.intrinsics == K and out.ground == {}
    assert (out.ground_alt, out.residual_px, out.gps_rms) == (180.5, 0.7, 1.2)
    np.testing.assert_array_equal(out.centres, geo.centres)


@pytest.mark.parametrize("mmap", [True, False])
def test_save_load_round_trip(tmp_path, mmap):
    geo = _geometry()
    geo.add_ground("sift", np.array([[150, 110, 1, 0], [10, 10, 1, 0], [170, 130, 1, 0]],
                                    np.float32), np.array([0, 2, 2, 3]))
    geo.add_ground("orb", np.zeros((0, 2), np.float32), np.array([0, 0, 0, 0]))
    geo.save(tmp_path)
    back = MapGeometry.load(tmp_path, mmap=mmap)
    assert isinstance(back.centres, np.memmap) is mmap
    assert isinstance(back.ground["sift"], np.memmap) is mmap
    np.testing.assert_array_equal(back.rotations, geo.rotations)
    np.testing.assert_array_equal(back.centres, geo.centres)
    assert back.intrinsics == K
    assert (back.ground_alt, back.residual_px, back.gps_rms) == (180.5, 0.7, 1.2)
    assert sorted(back.ground) == ["orb", "sift"]
    np.testing.assert_array_equal(back.ground["sift"], geo.ground["sift"])
    assert back.ground["orb"].shape == (0, 2)
    assert back.reconstructed.tolist() == [True, False, True]


def test_save_load_keeps_unknown_figures_unknown(tmp_path):
    geo = MapGeometry(np.full((1, 3, 3), np.nan), np.full((1, 3), np.nan), K,
                      float("nan"), float("nan"), float("inf"))
    geo.save(tmp_path)
    back = MapGeometry.load(tmp_path, mmap=False)
    assert math.isnan(back.ground_alt) and math.isnan(back.residual_px)
    assert math.isnan(back.gps_rms)  # infinite is not a figure JSON keeps either
    assert back.ground == {}


def test_load_of_a_folder_without_geometry_is_none(tmp_path):
    assert MapGeometry.load(tmp_path) is None
