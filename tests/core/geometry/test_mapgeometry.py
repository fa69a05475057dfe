"""A map's camera geometry: every keypoint's 3-D point, the frame priors, persistence."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

from tests.core.geometry.scene import level_rotation, tilted_rotation
from vloc.workers.core.geometry.camera import Intrinsics, nadir_rotation, project
from vloc.workers.core.geometry.mapgeometry import (
    DEPTH_NEIGHBOURS,
    DEPTH_RADIUS_PX,
    EXACT_PX,
    MapGeometry,
)
from vloc.workers.core.geometry.models import Structure

K = Intrinsics(100.0, 159.5, 119.5)


def _geometry(k1: float = 0.0) -> MapGeometry:
    """Three map images: a nadir camera, one not reconstructed, a tilted one."""
    rotations = np.stack([nadir_rotation(0.0), np.full((3, 3), np.nan),
                          tilted_rotation(2.0, 8.0, 1.0)])
    centres = np.array([[10.0, 20.0, 250.0], [np.nan] * 3, [-30.0, 5.0, 235.0]])
    return MapGeometry(rotations, centres, K, k1=k1, residual_px=0.7, gps_rms=1.2,
                       gps_rms_v=3.4, models=2)


def _pixels(geo, i, X):
    """Where map image ``i`` sees points X (n, 3), its distortion included."""
    R, C = geo.rotations[i], geo.centres[i]
    rvec, _ = cv2.Rodrigues(R)
    px, _ = cv2.projectPoints(np.asarray(X, np.float64), rvec, -R @ C, K.matrix,
                              geo.distortion)
    return px.reshape(-1, 2)


def _reference_points(geo, keypoints, offsets, seen):
    """The slow obvious reference of add_points: per keypoint, the 3-D point of a tie point
    of its image within EXACT_PX; else the tie points within DEPTH_RADIUS_PX, the
    DEPTH_NEIGHBOURS nearest of them, their median depth, and the point at that depth on the
    keypoint's ray (undistorted by iteration)."""
    out = np.full((len(keypoints), 3), np.nan)
    for i in range(len(offsets) - 1):
        R, C = geo.rotations[i], geo.centres[i]
        px, xyz = seen[i]
        if not np.isfinite(C).all() or len(px) < 3:
            continue
        for row in range(offsets[i], offsets[i + 1]):
            d = [(math.dist(keypoints[row, :2], p), k) for k, p in enumerate(px)]
            near = sorted(x for x in d if x[0] <= DEPTH_RADIUS_PX)[:DEPTH_NEIGHBOURS]
            if not near:
                continue
            if near[0][0] <= EXACT_PX:
                out[row] = xyz[near[0][1]]
                continue
            depth = float(np.median([(xyz[k] - C) @ R[2] for _, k in near]))
            u = (keypoints[row, 0] - K.cx) / K.f
            v = (keypoints[row, 1] - K.cy) / K.f
            x, y = u, v
            for _ in range(50):  # u = x (1 + k1 r^2): fixed-point iteration
                r2 = x * x + y * y
                x, y = u / (1 + geo.k1 * r2), v / (1 + geo.k1 * r2)
            out[row] = C + depth * np.array([x, y, 1.0]) @ R
    return out


def _scene(rng, geo):
    """Tie points of images 0 and 2 on a bumpy surface, and stored keypoints: some of them
    on tie points, the rest anywhere."""
    seen, keypoints, offsets = [], [], [0]
    for i in range(3):
        if not geo.reconstructed[i]:
            seen.append((np.zeros((0, 2)), np.zeros((0, 3))))
            kp = rng.uniform(0, 240, (5, 2))
        else:
            R, C = geo.rotations[i], geo.centres[i]
            px = np.column_stack([rng.uniform(0, 319, 60), rng.uniform(0, 239, 60)])
            depth = rng.uniform(30.0, 60.0, 60)
            rays = cv2.undistortPoints(px.reshape(-1, 1, 2), K.matrix,
                                       geo.distortion).reshape(-1, 2)
            xyz = C + (depth[:, None] * np.column_stack([rays, np.ones(60)])) @ R
            seen.append((px, xyz))
            kp = np.concatenate([px[:10], rng.uniform([0, 0], [319, 239], (30, 2))])
        keypoints.append(np.column_stack([kp, np.full((len(kp), 2), 3.0)]))
        offsets.append(offsets[-1] + len(kp))
    return np.concatenate(keypoints).astype(np.float32), np.array(offsets), seen


@pytest.mark.parametrize("k1", [0.0, -0.02])
def test_add_points_against_a_slow_reference(k1):
    rng = np.random.default_rng(0)
    geo = _geometry(k1)
    keypoints, offsets, seen = _scene(rng, geo)
    geo.add_points("sift", keypoints, offsets, seen)
    points = geo.points["sift"]
    assert points.dtype == np.float32 and points.shape == (len(keypoints), 3)
    want = _reference_points(geo, keypoints.astype(np.float64), offsets, seen)
    np.testing.assert_array_equal(np.isnan(points), np.isnan(want))
    np.testing.assert_allclose(points, want, atol=2e-3)
    # image 1 has no camera; some keypoints of the others lie far from every tie point
    assert np.isnan(points[offsets[1]:offsets[2]]).all()
    assert 0 < np.isnan(points[:offsets[1], 0]).sum() < 30
    # keypoints on tie points get exactly their 3-D points, other tie points near or not
    for i in (0, 2):
        px, xyz = seen[i]
        gaps = np.linalg.norm(px[:10, None] - px[None], axis=2)
        assert (np.sort(gaps, axis=1)[:, 1] <= DEPTH_RADIUS_PX).any()  # some have neighbours
        np.testing.assert_allclose(points[offsets[i]:offsets[i] + 10], xyz[:10], atol=2e-3)
    # ... and every other point lies on its own keypoint's ray
    for i in (0, 2):
        rows = np.arange(offsets[i], offsets[i + 1])
        ok = rows[np.isfinite(points[rows, 0])]
        np.testing.assert_allclose(_pixels(geo, i, points[ok]), keypoints[ok, :2], atol=0.02)


def test_add_points_known_answer_on_a_nadir_camera():
    # nadir, heading 0, 250 m up, f = 100: tie points on flat ground at 200 m (50 m below);
    # a keypoint a focal length right of the centre lies 50 m east on that ground
    geo = _geometry()
    tie_px = np.array([[159.5, 119.5], [259.5, 119.5], [159.5, 219.5], [109.5, 69.5]])
    ground = np.array([[10.0, 20.0, 200.0], [60.0, 20.0, 200.0], [10.0, -30.0, 200.0],
                       [-15.0, 45.0, 200.0]])
    np.testing.assert_allclose(project(geo.rotations[0], geo.centres[0], K, ground), tie_px)
    kp = np.array([[159.5, 119.5, 1, 0], [169.5, 119.5, 1, 0], [259.5, 129.5, 1, 0],
                   [0.0, 0.0, 1, 0]], np.float32)
    seen = [(tie_px, ground), (np.zeros((0, 2)), np.zeros((0, 3))),
            (np.zeros((0, 2)), np.zeros((0, 3)))]
    geo.add_points("orb", kp, np.array([0, 4, 4, 4]), seen)
    np.testing.assert_allclose(geo.points["orb"][:3],
                               [[10, 20, 200], [15, 20, 200], [60, 15, 200]], atol=1e-4)
    assert np.isnan(geo.points["orb"][3]).all()  # 100 px from every tie point
    # an image with fewer than three tie points places nothing
    seen[0] = (tie_px[:2], ground[:2])
    geo.add_points("orb", kp, np.array([0, 4, 4, 4]), seen)
    assert np.isnan(geo.points["orb"]).all()


def test_add_points_meets_the_plane_of_an_image_that_sees_one():
    # a nadir camera 50 m over level ground (200 m) whose tie points all lie on it: a
    # keypoint far from every tie point meets that ground; over relief it gets no point
    geo = _geometry()
    rng = np.random.default_rng(3)
    R, C = geo.rotations[0], geo.centres[0]
    tie_px = np.column_stack([rng.uniform(0, 140, 30), rng.uniform(0, 100, 30)])
    ground = C + (50.0 * geo.rays(tie_px)) @ R
    np.testing.assert_allclose(ground[:, 2], 200.0)
    kp = np.array([[300.0, 220.0, 1, 0], [159.5, 119.5, 1, 0]], np.float32)
    nothing = (np.zeros((0, 2)), np.zeros((0, 3)))
    geo.add_points("sift", kp, np.array([0, 2, 2, 2]), [(tie_px, ground), nothing, nothing])
    # 140.5 and 100.5 px from the centre, f = 100 px, 50 m down; heading 0: y is south
    np.testing.assert_allclose(geo.points["sift"],
                               [[10.0 + 70.25, 20.0 - 50.25, 200.0], [10.0, 20.0, 200.0]],
                               atol=1e-3)
    hills = ground.copy()
    hills[:, 2] += rng.uniform(-10.0, 10.0, len(hills))  # a fifth of the depth
    geo.add_points("sift", kp, np.array([0, 2, 2, 2]), [(tie_px, hills), nothing, nothing])
    assert np.isnan(geo.points["sift"]).all()


def test_rays_known_answer():
    geo = _geometry()
    np.testing.assert_allclose(geo.rays(np.array([[159.5, 119.5], [259.5, 69.5]])),
                               [[0, 0, 1], [1, -0.5, 1]], atol=1e-12)
    # with distortion: the ray of a distorted pixel is the undistorted direction
    geo.k1 = -0.1
    x = np.array([0.6, -0.3])
    r2 = x @ x
    px = x * (1 - 0.1 * r2) * K.f + [K.cx, K.cy]
    np.testing.assert_allclose(geo.rays(px[None])[0], [*x, 1.0], atol=1e-6)
    np.testing.assert_array_equal(geo.distortion, [-0.1, 0, 0, 0])


def test_altitude_range():
    geo = _geometry()
    assert geo.reconstructed.tolist() == [True, False, True]
    # cameras at 235 and 250 m: half their span is under 20 m, so 20 m either way
    assert geo.altitude_range() == pytest.approx((215.0, 270.0))
    geo.centres = np.array([[0, 0, 200.0], [0, 0, 300.0], [np.nan] * 3])
    geo.rotations = np.stack([nadir_rotation(0.0)] * 2 + [np.full((3, 3), np.nan)])
    assert geo.altitude_range() == pytest.approx((150.0, 350.0))
    none = MapGeometry(np.full((2, 3, 3), np.nan), np.full((2, 3), np.nan), K)
    assert none.altitude_range() == (0.0, 0.0)


def _with_views(rotations):
    n = len(rotations)
    return MapGeometry(np.stack(rotations), np.zeros((n, 3)), K)


def test_view_prior_of_a_nadir_map():
    # four cameras tilted 8 degrees, north, east, south and west: on average straight down,
    # each 8 degrees from it
    views = [tilted_rotation(0.0, 8.0, a) for a in (0.0, np.pi / 2, np.pi, 3 * np.pi / 2)]
    direction, sigma = _with_views(views).view_prior()
    np.testing.assert_allclose(direction, [0, 0, -1], atol=1e-12)
    assert sigma == pytest.approx(8.0)
    # straight down: at least 5 degrees
    direction, sigma = _with_views([nadir_rotation(t) for t in (0.0, 1.0, 2.0)]).view_prior()
    np.testing.assert_allclose(direction, [0, 0, -1], atol=1e-12)
    assert sigma == 5.0


def test_view_prior_of_an_oblique_survey_and_none_for_a_street():
    # a fixed gimbal 30 degrees off nadir, looking north: that is the prior
    oblique = [level_rotation(np.pi / 2 + d, pitch_deg=-60.0) for d in (-0.02, 0.0, 0.02)]
    direction, sigma = _with_views(oblique).view_prior()
    np.testing.assert_allclose(direction, [0, 0.5, -math.sqrt(3) / 2], atol=1e-3)
    assert sigma == 5.0
    # a walker looking along the street both ways, and at the facades
    street = [level_rotation(a) for a in np.radians([0.0, 10.0, 90.0, 180.0, 270.0])]
    assert _with_views(street).view_prior() is None
    # a survey that turns its camera 20 degrees from down in places
    turning = [nadir_rotation(0.0)] * 3 + [tilted_rotation(0.0, 40.0, 0.0)]
    assert _with_views(turning).view_prior() is None
    # too few cameras to say
    assert _with_views([nadir_rotation(0.0)] * 2).view_prior() is None


def test_base_sigma_comes_from_the_self_check():
    geo = _geometry()
    assert geo.base_sigma == 2.0
    geo.self_check = {"sigma_m": 3.25}
    assert geo.base_sigma == 3.25
    geo.self_check = {"sigma_m": math.nan}
    assert geo.base_sigma == 2.0


def test_from_structure_carries_every_field():
    geo = _geometry()
    st = Structure(geo.rotations, geo.centres, K, -0.02, [np.zeros(0, np.int64)] * 3,
                   [np.zeros((0, 3))] * 3, residual_px=0.7, gps_rms_h=1.2, gps_rms_v=3.4,
                   models=2)
    out = MapGeometry.from_structure(st)
    assert out.intrinsics == K and out.points == {} and out.self_check == {}
    assert (out.k1, out.residual_px, out.gps_rms, out.gps_rms_v, out.models) == \
        (-0.02, 0.7, 1.2, 3.4, 2)
    np.testing.assert_array_equal(out.centres, geo.centres)
    np.testing.assert_array_equal(out.rotations, geo.rotations)


@pytest.mark.parametrize("mmap", [True, False])
def test_save_load_round_trip(tmp_path, mmap):
    geo = _geometry(k1=-0.03)
    rng = np.random.default_rng(1)
    keypoints, offsets, seen = _scene(rng, geo)
    geo.add_points("sift", keypoints, offsets, seen)
    geo.points["orb"] = np.zeros((0, 3), np.float32)
    geo.self_check = {"images": 3, "median_m": 0.8, "trusted": True, "sigma_m": 2.0}
    geo.save(tmp_path)
    back = MapGeometry.load(tmp_path, mmap=mmap)
    assert isinstance(back.centres, np.memmap) is mmap
    assert isinstance(back.points["sift"], np.memmap) is mmap
    np.testing.assert_array_equal(back.rotations, geo.rotations)
    np.testing.assert_array_equal(back.centres, geo.centres)
    assert back.intrinsics == K
    assert (back.k1, back.residual_px, back.gps_rms, back.gps_rms_v, back.models) == \
        (-0.03, 0.7, 1.2, 3.4, 2)
    assert sorted(back.points) == ["orb", "sift"]
    np.testing.assert_array_equal(back.points["sift"], geo.points["sift"])
    assert back.points["orb"].shape == (0, 3)
    assert back.self_check == geo.self_check
    assert back.reconstructed.tolist() == [True, False, True]
    assert json.loads((tmp_path / "geometry.json").read_text())["format"] == 2


def test_save_load_keeps_unknown_figures_unknown(tmp_path):
    geo = MapGeometry(np.full((1, 3, 3), np.nan), np.full((1, 3), np.nan), K,
                      residual_px=float("nan"), gps_rms=float("inf"))
    geo.save(tmp_path)
    back = MapGeometry.load(tmp_path, mmap=False)
    assert math.isnan(back.residual_px) and math.isnan(back.gps_rms_v)
    assert math.isnan(back.gps_rms)  # infinite is not a figure JSON keeps either
    assert back.points == {} and back.self_check == {} and back.base_sigma == 2.0


def _save_plane_format(folder, ground_alt):
    """A folder as the ground-plane geometry (format 1) saved it: camera heights above the
    plane, keypoints' east/north on it."""
    rotations = np.stack([nadir_rotation(0.3), np.full((3, 3), np.nan)])
    np.save(folder / "geometry_rotations.npy", rotations)
    np.save(folder / "geometry_centres.npy", np.array([[1.0, 2.0, 50.0], [np.nan] * 3]))
    np.save(folder / "geometry_ground_sift.npy",
            np.array([[3.0, 4.0], [np.nan, np.nan], [-5.0, 6.5]], np.float32))
    meta = {"f": 250.0, "cx": 160.0, "cy": 120.0, "residual_px": 0.5, "gps_rms": 1.5,
            "ground": ["sift"]}
    if ground_alt is not None:
        meta["ground_alt"] = ground_alt
    (folder / "geometry.json").write_text(json.dumps(meta))
    return rotations


@pytest.mark.parametrize(("ground_alt", "altitude"), [(180.5, 180.5), (None, 0.0)])
def test_a_plane_format_folder_loads_as_points_on_its_ground(tmp_path, ground_alt, altitude):
    rotations = _save_plane_format(tmp_path, ground_alt)
    geo = MapGeometry.load(tmp_path)
    np.testing.assert_array_equal(geo.rotations, rotations)
    np.testing.assert_array_equal(geo.centres[0], [1.0, 2.0, 50.0 + altitude])
    assert np.isnan(geo.centres[1]).all()
    points = geo.points["sift"]
    assert points.dtype == np.float32 and points.shape == (3, 3)
    np.testing.assert_array_equal(points[[0, 2]], [[3.0, 4.0, altitude], [-5.0, 6.5, altitude]])
    assert np.isnan(points[1, :2]).all()
    assert geo.intrinsics == Intrinsics(250.0, 160.0, 120.0)
    assert (geo.k1, geo.residual_px, geo.gps_rms) == (0.0, 0.5, 1.5)
    assert geo.self_check == {}
    # the map's cameras 50 m above that ground: altitudes around there are plausible
    lo, hi = geo.altitude_range()
    assert lo < 50.0 + altitude < hi


def test_load_of_a_folder_without_geometry_is_none(tmp_path):
    assert MapGeometry.load(tmp_path) is None
