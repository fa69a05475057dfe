"""The synthetic world generator: geometry, rendering, lighting and the data set it writes."""

from __future__ import annotations

import csv
import hashlib
import json
import math
from datetime import datetime
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from vloc.clients.cli import main
from vloc.clients.world import DEFAULT_ORIGIN, generate_world
from vloc.clients.world.camera import Camera, Pose, project
from vloc.clients.world.lighting import ILLUMINATIONS, shadow_mask
from vloc.clients.world.render import Renderer
from vloc.clients.world.routes import lawnmower, rounded_rectangle
from vloc.clients.world.scene import Plane, box_corners, box_solid, ground_plane, plane_from_rect
from vloc.workers.core.exif import read_gps
from vloc.workers.core.sift import extract_sift, match_share

HEADER = ["filename", "pass", "captured_at", "lat", "lon", "alt_m"]


def _rows(path: Path) -> list[dict]:
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def _digest(folder: Path) -> dict[str, str]:
    files = sorted(folder.glob("images/*.jpg")) + sorted(folder.glob("*.csv"))
    files.append(folder / "world.json")
    return {f.name: hashlib.sha256(f.read_bytes()).hexdigest() for f in files}


@pytest.fixture(scope="module")
def robot_world(tmp_path_factory):
    """A short robot round (45 frames, 27 m) under the three illuminations."""
    out = tmp_path_factory.mktemp("robot")
    info = generate_world(out, kind="robot", seed=11, passes=["sunny", "cloudy", "dusk"],
                          frames=45, gps_noise_m=0.5)
    return info


# -- geometry: known answers ---------------------------------------------------------------

def test_camera_focal_and_projection():
    cam = Camera(320, 240, 60.0)
    assert cam.focal == pytest.approx(160.0 / math.tan(math.radians(30.0)))
    pose = Pose(np.array([1.0, 2.0, 1.5]), yaw=math.pi / 2)           # looking north
    uv, depth = project(cam, pose, np.array([[1.0, 12.0, 1.5], [2.0, 12.0, 1.5],
                                             [1.0, 12.0, 2.5]]))
    assert depth == pytest.approx([10.0, 10.0, 10.0])
    assert uv[0] == pytest.approx([159.5, 119.5])                     # principal point
    assert uv[1, 0] > 159.5                                           # east is right
    assert uv[2, 1] < 119.5                                           # up is up
    assert uv[1, 0] - 159.5 == pytest.approx(cam.focal / 10.0)
    assert pose.heading_deg == pytest.approx(0.0)
    assert Pose(np.zeros(3), yaw=0.0).heading_deg == pytest.approx(90.0)


def test_nadir_camera_sees_heading_at_the_top():
    cam = Camera()
    pose = Pose(np.array([0.0, 0.0, 20.0]), yaw=0.0, pitch=-math.pi / 2)  # flying east
    uv, depth = project(cam, pose, np.array([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0], [0.0, 5.0, 0.0]]))
    assert depth[0] == pytest.approx(20.0)
    assert uv[0] == pytest.approx([159.5, 119.5])
    assert uv[1, 1] < 119.5 and uv[1, 0] == pytest.approx(159.5)    # ahead: image top
    assert uv[2, 0] < 159.5                                           # left of track: left


def test_rounded_rectangle_length_and_closure():
    hx, hy, r = 40.0, 25.0, 4.5
    route = rounded_rectangle(hx, hy, r)
    assert route.closed
    # Straight parts 2 (2hx - 2r) + 2 (2hy - 2r) plus a full circle of radius r.
    assert route.length == pytest.approx(4 * (hx + hy) - 8 * r + 2 * math.pi * r, rel=1e-3)
    xy, tangent = route.at(np.array([0.0, route.length]))
    assert xy[0] == pytest.approx(xy[1])
    assert tangent[0] == pytest.approx([1.0, 0.0], abs=1e-6)         # anticlockwise start


def test_lawnmower_lanes():
    route = lawnmower(50.0, 20.0, 10.0)
    assert not route.closed
    # Three lanes of 50 m and two half circles of radius 5 m.
    assert route.length == pytest.approx(150.0 + 2 * math.pi * 5.0, rel=1e-3)
    assert route.points[:, 1].max() == pytest.approx(20.0)


def test_box_shadow_length_follows_sun_elevation():
    """A 3 m box under a sun 45 degrees high in the south throws a 3 m shadow north."""
    illum = ILLUMINATIONS["sunny"]
    illum = type(illum)(**{**illum.to_json(), "sun_azimuth_deg": 180.0,
                           "sun_elevation_deg": 45.0, "penumbra_m": 0.0})
    texel = 0.05
    ground = ground_plane(np.full((200, 200, 3), 128, np.uint8), np.array([-5, -5, 5, 5]), texel)
    box = box_solid(box_corners(np.array([0.0, -2.0, 0.0]), np.array([0.5, 0.5, 3.0]), 0.0), 7)
    mask = shadow_mask(ground, [box], illum, np.random.default_rng(0))

    def at(x, y):
        c, r = ground.texel_of(np.array([[x, y, 0.0]]))[0]
        return mask[int(round(r)), int(round(c))]

    assert at(0.0, -1.0) == 1.0                 # just north of the box
    assert at(0.0, -2.0 + 0.5 + 3.0 - 0.2) == 1.0   # near the tip: 3 m beyond the north face
    assert at(0.0, -2.0 + 0.5 + 3.0 + 0.3) == 0.0   # past the tip
    assert at(0.0, -3.0) == 0.0                 # south of the box: lit
    assert at(1.0, -1.0) == 0.0                 # beside the shadow


# -- renderer: cross-checked against per-pixel ray casting -----------------------------------

def _reference_render(cam: Camera, pose: Pose, plane: Plane, texture: np.ndarray) -> tuple:
    """Cast a ray through every pixel, intersect the plane, sample bilinearly."""
    k_inv = np.linalg.inv(cam.matrix)
    R = pose.rotation()
    out = np.zeros((cam.height, cam.width, 3))
    hit = np.zeros((cam.height, cam.width), bool)
    n = plane.normal
    h, w = texture.shape[:2]
    for y in range(cam.height):
        for x in range(cam.width):
            d = R.T @ (k_inv @ np.array([x, y, 1.0]))
            t = n @ (plane.origin - pose.position) / (n @ d)
            if t <= 0:
                continue
            c, r = plane.texel_of((pose.position + t * d)[None])[0]
            if not (0.5 <= c <= w - 1.5 and 0.5 <= r <= h - 1.5):
                continue
            c0, r0 = int(c), int(r)
            fc, fr = c - c0, r - r0
            out[y, x] = ((1 - fc) * (1 - fr) * texture[r0, c0] + fc * (1 - fr) * texture[r0, c0 + 1]
                         + (1 - fc) * fr * texture[r0 + 1, c0] + fc * fr * texture[r0 + 1, c0 + 1])
            hit[y, x] = True
    return out, hit


def test_renderer_matches_ray_casting():
    rng = np.random.default_rng(3)
    texture = cv2.resize(rng.integers(0, 256, (12, 16, 3)).astype(np.uint8), (64, 48),
                         interpolation=cv2.INTER_LINEAR)
    # A 3.2 m x 2.4 m quad 4 m ahead of the camera, turned 30 degrees: texels (5 cm) are
    # larger than pixels (1.4 cm at 4 m), so the base mip level is used.
    yaw = math.radians(30.0)
    right = np.array([math.sin(yaw), -math.cos(yaw), 0.0])
    centre = np.array([4.0, 0.0, 1.0])
    plane = plane_from_rect(centre - right * 1.6 + np.array([0, 0, 1.2]), right,
                            np.array([0.0, 0.0, -1.0]), 3.2, 2.4, texture)
    cam = Camera(80, 60, 60.0)
    pose = Pose(np.array([0.0, 0.2, 1.1]), yaw=0.05, pitch=-0.03, roll=0.02)
    sky = np.zeros((256, 1024, 3), np.uint8)
    fast = Renderer(cam, [plane], [texture], sky, supersample=1).render(pose).astype(float)
    slow, hit = _reference_render(cam, pose, plane, texture.astype(float))
    inner = cv2.erode(hit.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    assert inner.sum() > 1000
    assert np.abs(fast - slow)[inner].mean() < 1.5
    # Nothing outside the quad (the reference leaves out its outer texel and a half).
    around = cv2.dilate(hit.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    assert (fast[~around] == 0).all()


def test_depth_buffer_hides_far_quads_whatever_the_order():
    near = plane_from_rect(np.array([5.0, 0.5, 1.5]), np.array([0.0, -1.0, 0.0]),
                           np.array([0.0, 0.0, -1.0]), 1.0, 1.0, np.full((8, 8, 3), 200, np.uint8))
    far = plane_from_rect(np.array([9.0, 3.0, 4.0]), np.array([0.0, -1.0, 0.0]),
                          np.array([0.0, 0.0, -1.0]), 6.0, 6.0, np.full((8, 8, 3), 60, np.uint8))
    cam, pose = Camera(64, 48, 60.0), Pose(np.array([0.0, 0.0, 1.0]), yaw=0.0)
    sky = np.zeros((256, 1024, 3), np.uint8)
    images = [Renderer(cam, planes, [p.albedo for p in planes], sky, supersample=1).render(pose)
              for planes in ([near, far], [far, near])]
    np.testing.assert_array_equal(images[0], images[1])
    uv, _ = project(cam, pose, np.array([[5.0, 0.0, 1.0]]))
    cx, cy = (int(round(v)) for v in uv[0])
    assert images[0][cy, cx][0] == 200
    assert images[0][cy, cx + 12][0] == 60               # beside the near quad: the far one


# -- the data set ----------------------------------------------------------------------------

def test_layout_and_ground_truth(robot_world):
    out = robot_world.out_dir
    with (out / "ground_truth.csv").open(newline="") as f:
        assert next(csv.reader(f)) == HEADER
    rows = _rows(out / "ground_truth.csv")
    assert len(rows) == 3 * 45 == robot_world.images
    assert sorted({r["pass"] for r in rows}) == ["1", "2", "3"]
    for r in rows:
        image = cv2.imread(str(out / "images" / r["filename"]))
        assert image.shape == (240, 320, 3)
        break
    times = [datetime.fromisoformat(r["captured_at"]) for r in rows if r["pass"] == "1"]
    assert rows[0]["captured_at"] == "2013-06-04T13:37:29.000"
    assert {(b - a).total_seconds() for a, b in zip(times[:-1], times[1:], strict=True)} == {1.0}
    meta = json.loads((out / "world.json").read_text())
    assert meta["kind"] == "robot" and meta["seed"] == 11
    assert [p["illumination"] for p in meta["passes"]] == ["sunny", "cloudy", "dusk"]
    assert meta["gps_noise"]["sigma_m"] == 0.5 and meta["route"]["closed"]


def test_robot_frames_are_0_6_m_apart_on_a_closed_round(robot_world):
    rows = _rows(robot_world.out_dir / "poses.csv")
    for p in ("1", "2", "3"):
        xy = np.array([[float(r["east_m"]), float(r["north_m"])] for r in rows if r["pass"] == p])
        steps = np.linalg.norm(np.diff(xy, axis=0), axis=1)
        assert steps.mean() == pytest.approx(0.6, rel=0.1)
        assert steps.min() > 0.3 and steps.max() < 0.9
        # One full round: the last frame is about one spacing short of the first.
        assert np.linalg.norm(xy[-1] - xy[0]) < 1.5
        assert steps.sum() + np.linalg.norm(xy[-1] - xy[0]) == pytest.approx(
            robot_world.route_length_m, rel=0.1)
        assert np.all(np.abs(np.array([float(r["up_m"]) for r in rows if r["pass"] == p]) - 1.0) < 0.05)


def test_exif_gps_round_trips(robot_world):
    out = robot_world.out_dir
    truth = {r["filename"]: r for r in _rows(out / "ground_truth.csv")}
    tags = {r["filename"]: r for r in _rows(out / "exif_gps.csv")}
    offsets = []
    for name, row in truth.items():
        gps = read_gps((out / "images" / name).read_bytes())
        assert gps is not None
        e, n = DEFAULT_ORIGIN.to_local(gps.lat, gps.lon)
        want = tags[name] if row["pass"] == "1" else row
        we, wn = DEFAULT_ORIGIN.to_local(float(want["lat"]), float(want["lon"]))
        assert math.hypot(float(e - we), float(n - wn)) < 0.01
        assert gps.alt == pytest.approx(float(row["alt_m"]), abs=0.01)
        assert gps.captured_at.replace(tzinfo=None) == datetime.fromisoformat(row["captured_at"])
        te, tn = DEFAULT_ORIGIN.to_local(float(row["lat"]), float(row["lon"]))
        offsets.append((row["pass"], float(e - te), float(n - tn)))
    map_noise = np.array([(de, dn) for p, de, dn in offsets if p == "1"])
    query_noise = np.array([(de, dn) for p, de, dn in offsets if p != "1"])
    assert np.abs(query_noise).max() < 0.01                 # query passes: the truth
    assert 0.3 < map_noise.std() < 0.7                      # map pass: sigma 0.5 m


def test_illuminations_differ_as_described(robot_world):
    stats = {}
    for p in ("1", "2", "3"):
        greys = [cv2.imread(str(f), cv2.IMREAD_GRAYSCALE).astype(float)
                 for f in sorted(robot_world.image_dir.glob(f"p{p}_*.jpg"))[::5]]
        stats[p] = (np.mean([g.mean() for g in greys]), np.mean([g.std() for g in greys]))
    assert stats["1"][1] > 1.3 * stats["2"][1]              # sunny: more contrast than cloudy
    assert stats["3"][0] < 0.8 * stats["2"][0]              # dusk: darker


def test_sift_matches_same_place_across_illumination(robot_world):
    out = robot_world.out_dir
    poses = _rows(out / "poses.csv")
    by_pass = {p: [(r["filename"], float(r["east_m"]), float(r["north_m"]))
                   for r in poses if r["pass"] == p] for p in ("1", "2")}
    cache = {}

    def feats(name):
        if name not in cache:
            cache[name] = extract_sift(cv2.imread(str(out / "images" / name), cv2.IMREAD_GRAYSCALE))
        return cache[name]

    other = np.array([[e, n] for _, e, n in by_pass["2"]])
    same, far, nearby = [], [], []
    for k in range(0, 44, 4):
        name, e, n = by_pass["1"][k]
        d = np.hypot(other[:, 0] - e, other[:, 1] - n)
        same.append(match_share(feats(name), feats(by_pass["2"][int(d.argmin())][0])))
        far.append(match_share(feats(name), feats(by_pass["2"][int(d.argmax())][0])))
        nearby.append(match_share(feats(name), feats(by_pass["1"][k + 1][0])))
    same, far = np.array(same), np.array(far)
    assert same.mean() > 1.6 * far.mean()
    assert (same > far).mean() >= 0.75
    assert np.mean(nearby) > 0.3 and np.mean(nearby) > 2 * far.mean()


def test_same_seed_same_bytes_and_other_seed_other_images(tmp_path):
    args = dict(kind="robot", passes=["sunny", "dusk"], frames=4, route_length=24.0)
    a = generate_world(tmp_path / "a", seed=5, **args)
    generate_world(tmp_path / "b", seed=5, **args)
    generate_world(tmp_path / "c", seed=6, **args)
    da, db, dc = (_digest(tmp_path / x) for x in "abc")
    assert len(da) == 2 * 4 + 4 and da == db
    jpgs = [k for k in da if k.endswith(".jpg")]
    assert all(da[k] != dc[k] for k in jpgs)
    assert a.frame_spacing_m == pytest.approx(6.0)


def test_uav_world(tmp_path):
    info = generate_world(tmp_path, kind="uav", seed=2, passes=["sunny", "cloudy"], frames=8,
                          altitude=30.0)
    poses = _rows(tmp_path / "poses.csv")
    up = np.array([float(r["up_m"]) for r in poses])
    assert np.all((up > 25.0) & (up < 35.0))
    pitch = np.array([float(r["pitch_deg"]) for r in poses])
    assert np.all(np.abs(pitch + 90.0) < 5.0)
    headings = {p: np.array([float(r["heading_deg"]) for r in poses if r["pass"] == p])
                for p in ("1", "2")}
    assert not np.allclose(headings["1"], headings["2"], atol=1.0)   # yaw differs per pass
    xy = np.array([[float(r["east_m"]), float(r["north_m"])] for r in poses if r["pass"] == "1"])
    steps = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    assert steps.mean() > 3.0 and steps.std() > 0.1 * steps.mean()  # far apart, uneven
    assert info.gps_noise_m == 2.0


def test_rejects_bad_arguments(tmp_path):
    with pytest.raises(ValueError, match="illumination"):
        generate_world(tmp_path, passes=["foggy"], frames=4)
    with pytest.raises(ValueError, match="kind"):
        generate_world(tmp_path, kind="boat", frames=4)
    generate_world(tmp_path, frames=2, route_length=24.0, passes=["cloudy"])
    with pytest.raises(FileExistsError):
        generate_world(tmp_path, frames=2, route_length=24.0, passes=["cloudy"])


def test_cli_writes_the_layout(tmp_path):
    out = tmp_path / "w"
    result = CliRunner().invoke(main, ["world", str(out), "--frames", "3", "--route-length", "24",
                                       "--passes", "sunny,cloudy", "--seed", "1", "--quiet"])
    assert result.exit_code == 0, result.output
    assert "6 images" in result.output
    assert len(list((out / "images").glob("*.jpg"))) == 6
    assert (out / "ground_truth.csv").read_text().splitlines()[0] == ",".join(HEADER)
    assert json.loads((out / "world.json").read_text())["passes"][1]["illumination"] == "cloudy"
    bad = CliRunner().invoke(main, ["world", str(tmp_path / "x"), "--passes", "sunny,foggy"])
    assert bad.exit_code != 0 and "foggy" in bad.output
