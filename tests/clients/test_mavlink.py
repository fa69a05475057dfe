"""``vloc mavlink`` against the simulated autopilot (a real MAVLink endpoint on UDP) and the
real service: every tracking pose reaches the autopilot as ``GPS_INPUT`` with the pose's
position and accuracy, nothing else does, and the autopilot's heading, altitude and velocity
reach the frames."""

from __future__ import annotations

import csv
import json
import math
import os
import subprocess
import sys
import threading
from datetime import UTC, datetime
from pathlib import Path

import pytest

pytest.importorskip("pymavlink", reason="the mavlink extra (pip install -e '.[dev]')")

from tests.clients.conftest import ADMIN_KEY, FAST, bare_environment  # noqa: E402
from tests.conftest import REPO_ROOT  # noqa: E402
from vloc.clients.mavlink_sim import SimulatedAutopilot  # noqa: E402
from vloc.clients.sdk import Client, Pose  # noqa: E402
from vloc.clients.sdk._frame_sources import Camera, capture_source  # noqa: E402
from vloc.clients.sdk._mavlink_messages import (  # noqa: E402
    FIX_2D,
    FIX_3D,
    IGNORE_ALT,
    RateLimiter,
    gps_input,
    gps_time,
    map_origin,
    odometry,
    vision_position_estimate,
)
from vloc.clients.sdk.mavlink import Bridge, BridgeOptions, Link, folder_frames  # noqa: E402

HEADING, ALTITUDE, VELOCITY = 87.5, 250.0, (3.0, -1.5)


def _pose(**over) -> Pose:
    base = {"seq": 4, "status": "tracking", "x": 12.0, "y": -30.0, "lat": 41.0341234567,
            "lon": -83.3051234567, "altitude_m": 280.0, "horizontal_accuracy_m": 6.5,
            "sigma_x": 4.0, "sigma_y": 5.0, "cov": (16.0, 2.0, 2.0, 25.0), "feature": "sift",
            "heading_deg": 55.0, "heading_sigma_deg": 2.0, "heading_source": "geometry"}
    return Pose.model_validate(base | over)


# -- the messages, by hand ------------------------------------------------------------------

def test_gps_input_carries_the_pose_to_1e7_degrees_and_its_accuracy():
    at = datetime(2024, 6, 4, 13, 0, 0, tzinfo=UTC)
    m = gps_input(_pose(), at=at)
    assert (m["lat"], m["lon"]) == (410341235, -833051235)
    assert (m["fix_type"], m["alt"], m["horiz_accuracy"]) == (FIX_3D, 280.0, 6.5)
    assert m["hdop"] == pytest.approx(6.5 / 3.0) and m["yaw"] == 5500
    assert m["time_usec"] == 1717506000 * 10**6
    # 2024-06-04 was a Tuesday of GPS week 2317; GPS time is UTC + 18 s
    assert (m["time_week"], m["time_week_ms"]) == (2317, (2 * 86400 + 13 * 3600 + 18) * 1000)
    no_alt = gps_input(_pose(altitude_m=None), at=at)
    assert no_alt["fix_type"] == FIX_2D and no_alt["ignore_flags"] & IGNORE_ALT
    assert gps_input(_pose(heading_deg=0.0), at=at)["yaw"] == 36000  # north, not "unknown"
    # the autopilot's own heading, sent with the frame, is not given back as a measurement
    assert gps_input(_pose(heading_source="device"), at=at)["yaw"] == 0
    for status in ("initialising", "lost"):
        assert gps_input(_pose(status=status), at=at) is None
        assert vision_position_estimate(_pose(status=status), usec=0) is None
        assert odometry(_pose(status=status), usec=0) is None


def test_gps_time_at_the_epoch_and_across_a_week():
    assert gps_time(datetime(1980, 1, 6, tzinfo=UTC)) == (0, 18_000)
    assert gps_time(datetime(1980, 1, 12, 23, 59, 50, tzinfo=UTC)) == (1, 8_000)


def test_local_estimates_are_north_east_down_with_the_pose_covariance():
    v = vision_position_estimate(_pose(), usec=5, reset_counter=2)
    assert (v["x"], v["y"], v["reset_counter"]) == (-30.0, 12.0, 2)
    assert (v["covariance"][0], v["covariance"][1], v["covariance"][6]) == (25.0, 2.0, 16.0)
    assert v["yaw"] == pytest.approx(math.radians(55.0))
    # ArduPilot's two noises from the diagonal: the horizontal one, the heading's sigma
    diagonal = [v["covariance"][i] for i in (0, 6, 11, 15, 18, 20)]
    assert diagonal == pytest.approx([25.0, 16.0, 0.0, 0.0, 0.0, math.radians(2.0) ** 2])
    blind = vision_position_estimate(_pose(heading_source="device"), usec=5)
    assert math.isnan(blind["yaw"]) and not any(map(math.isnan, blind["covariance"]))
    assert blind["covariance"][20] == pytest.approx(math.pi ** 2 / 3)
    o = odometry(_pose(heading_source=None, heading_deg=None), usec=5)
    assert (o["x"], o["y"]) == (-30.0, 12.0) and math.isnan(o["q"][0])
    assert math.isnan(o["vx"]) and o["pose_covariance"][0] == 25.0


def test_the_map_origin_from_one_pose_is_the_tangent_planes():
    from vloc.workers.core.geo import GeoOrigin

    origin = GeoOrigin(41.0345, -83.3057, 0.0)
    east, north = origin.to_local([41.0361], [-83.3031])
    pose = _pose(x=float(east[0]), y=float(north[0]), lat=41.0361, lon=-83.3031)
    lat, lon = map_origin(pose)
    assert abs(lat - 41.0345) < 1e-7 and abs(lon + 83.3057) < 1e-7


def test_the_rate_limiter_drops_what_comes_too_soon():
    now = [0.0]
    limit = RateLimiter(2.0, clock=lambda: now[0])
    allowed = []
    for t in (0.0, 0.1, 0.49, 0.5, 0.9, 1.2, 5.0):
        now[0] = t
        allowed.append(limit.allow())
    assert allowed == [True, False, False, True, False, True, True]


# -- the bridge against the simulated autopilot and the service -----------------------------

@pytest.fixture(scope="module")
def flight(live_server, shots, tmp_path_factory):
    """A map built from the synthetic map shots, and the query shots as a folder."""
    maps, queries = shots
    with Client(live_server, admin_key=ADMIN_KEY) as vloc:
        m = vloc.create_map("mavlink")
        vloc.upload_images(m.id, [(s.name, s.jpeg) for s in maps])
        vloc.wait_for_job(vloc.build_map(m.id).id, timeout=120)
    folder = tmp_path_factory.mktemp("flight")
    for s in queries:
        (folder / s.name).write_bytes(s.jpeg)
    return m.id, folder


@pytest.fixture
def autopilot():
    sim = SimulatedAutopilot()
    sim.state.heading_deg, sim.state.altitude_m = HEADING, ALTITUDE
    sim.state.velocity_en = VELOCITY
    with sim:
        yield sim


def _session(base: str, map_id: str) -> tuple[str, str]:
    with Client(base, admin_key=ADMIN_KEY) as vloc:
        s = vloc.create_session(map_id, params=FAST, seed=3)
    return s.id, s.token


def _server_poses(base: str, session_id: str) -> dict[int, Pose]:
    with Client(base, admin_key=ADMIN_KEY) as vloc:
        return {p.seq: p for p in vloc.list_poses(session_id) if p.type == "pose"}


def check_messages(sim: SimulatedAutopilot, records: list[dict], poses: dict[int, Pose]):
    """Each GPS_INPUT the autopilot got is the pose of the frame the bridge sent it for,
    to 1e-7 degrees and to float32 in its accuracy; no pose that was not tracking sent
    one. Returns (message, pose) pairs."""
    sent = {r["sent"]["time_usec"]: r for r in records if "sent" in r}
    got = sim.received("GPS_INPUT")
    assert len(got) == len(sent)
    pairs = []
    for msg in got:
        pose = poses[sent[msg.fields["time_usec"]]["seq"]]
        assert pose.status == "tracking"
        assert (msg.fields["lat"], msg.fields["lon"]) == (round(pose.lat * 1e7),
                                                          round(pose.lon * 1e7))
        assert abs(msg.fields["lat"] / 1e7 - pose.lat) <= 0.5e-7
        assert msg.fields["horiz_accuracy"] == pytest.approx(pose.horizontal_accuracy_m,
                                                             rel=1e-6)
        assert msg.fields["hdop"] == pytest.approx(pose.horizontal_accuracy_m / 3.0, rel=1e-6)
        assert msg.fields["fix_type"] == (FIX_3D if pose.altitude_m is not None else FIX_2D)
        pairs.append((msg, pose))
    for r in records:
        if r.get("status") in ("initialising", "lost"):
            assert "sent" not in r and r["why"].startswith("no fix")
    return pairs


def test_vloc_mavlink_forwards_tracking_poses_and_gives_the_autopilots_heading(
        live_server, flight, autopilot, tmp_path):
    map_id, folder = flight
    session_id, token = _session(live_server, map_id)
    log = tmp_path / "bridge.jsonl"
    run = subprocess.run(
        [sys.executable, "-m", "vloc.clients.cli", "mavlink", str(folder), "--mavlink",
         autopilot.address, "--server", live_server, "--session", session_id, "--token",
         token, "--fps", "4", "--max-rate", "10", "--max-age", "30", "--log", str(log)],
        cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    records = [json.loads(line) for line in log.read_text().splitlines()]
    poses = _server_poses(live_server, session_id)
    assert len(records) == len(poses) == len(list(folder.iterdir()))
    pairs = check_messages(autopilot, records, poses)
    assert len(pairs) >= 3, [r.get("why") for r in records]
    # the autopilot's values reached every frame sent after its streams began
    assert all(p.altitude_m == ALTITUDE for p in poses.values())
    device = [p for p in poses.values() if p.heading_source == "device"]
    assert all(p.heading_deg == pytest.approx(HEADING) for p in device)
    assert all(r["metadata"] == pytest.approx({
        "heading_deg": HEADING, "altitude_m": ALTITUDE, "velocity_east": VELOCITY[0],
        "velocity_north": VELOCITY[1]}) for r in records)
    assert f"{len(pairs)} poses sent" in run.stderr


def _run_bridge(base, session_id, token, sim, folder, options, *, frames, during=None):
    """The bridge in this process over ``frames`` frames; ``during(i)`` runs before
    frame ``i``. Returns its log records."""
    records: list[dict] = []
    with Client(base, retry=0) as vloc, Link(sim.address, heartbeat_timeout_s=1.5) as link:
        bridge = Bridge(vloc, session_id, token, link, options, log=records.append)
        assert link.wait_alive(10.0)
        source = folder_frames(folder, loop=True)
        for i in range(frames):
            if during is not None:
                during(i, link)
            bridge.run([next(source)])
    return records


def test_a_dropped_link_resumes_without_a_stale_message(live_server, flight, autopilot):
    map_id, folder = flight
    session_id, token = _session(live_server, map_id)
    options = BridgeOptions(fps=10.0, max_rate_hz=20.0, max_pose_age_s=1.0)
    gap: dict[str, float] = {}

    def during(i: int, link: Link) -> None:
        waiter = threading.Event()
        if i == 12:
            autopilot.drop_link()
            gap["dropped"] = datetime.now(UTC).timestamp()
            while link.alive():  # the bridge notices by the heartbeats' absence
                waiter.wait(0.05)
        if i == 18:
            gap["restored"] = datetime.now(UTC).timestamp()
            autopilot.restore_link()
            while not link.alive():
                waiter.wait(0.05)

    records = _run_bridge(live_server, session_id, token, autopilot, folder, options,
                          frames=30, during=during)
    poses = _server_poses(live_server, session_id)
    pairs = check_messages(autopilot, records, poses)
    before = [m for m, _ in pairs if m.wall < gap["dropped"]]
    after = [m for m, _ in pairs if m.wall > gap["restored"]]
    assert before and after and len(before) + len(after) == len(pairs)
    for msg, _ in pairs:  # nothing older than the bridge's bound reached the autopilot
        assert msg.wall - msg.fields["time_usec"] / 1e6 <= options.max_pose_age_s + 0.1
    assert all(m.fields["time_usec"] / 1e6 > gap["dropped"] for m in after)
    assert any(r.get("why") == "link down" for r in records)
    # while the link was down the frames went without the autopilot's stale values
    assert any(r["metadata"] == {} for r in records)


def test_messages_keep_to_the_rate_the_autopilot_expects(live_server, flight, autopilot):
    map_id, folder = flight
    session_id, token = _session(live_server, map_id)
    options = BridgeOptions(fps=20.0, max_rate_hz=2.0, max_pose_age_s=5.0)
    records = _run_bridge(live_server, session_id, token, autopilot, folder, options,
                          frames=24)
    poses = _server_poses(live_server, session_id)
    pairs = check_messages(autopilot, records, poses)
    arrivals = [m.at for m, _ in pairs]
    assert len(arrivals) >= 2 and any(r.get("why") == "rate" for r in records)
    # at most max_rate_hz: the sends are 1 / 2 s apart at least (less the loopback's jitter)
    assert min(b - a for a, b in zip(arrivals, arrivals[1:], strict=False)) >= 0.5 - 0.05


@pytest.mark.parametrize("output", ["vision", "odometry"])
def test_local_estimates_reach_the_autopilot_in_the_maps_frame(live_server, flight, shots,
                                                                autopilot, tmp_path, output):
    """``--output vision`` / ``odometry`` as the autopilot takes them: the EKF origin the
    bridge set is the map's, each estimate's north-east metres from it are the pose's
    position and near the frame's truth, and its covariance is the pose's (the 68 % circle
    it gives is the pose's ``horizontal_accuracy_m``)."""
    from vloc.clients.mavlink_sim import ExternalNav
    from vloc.workers.core.accuracy import horizontal_accuracy
    from vloc.workers.core.geo import GeoOrigin

    map_id, folder = flight
    truth = {s.name: s for s in shots[1]}
    session_id, token = _session(live_server, map_id)
    log = tmp_path / "bridge.jsonl"
    run = subprocess.run(
        [sys.executable, "-m", "vloc.clients.cli", "mavlink", str(folder), "--mavlink",
         autopilot.address, "--server", live_server, "--session", session_id, "--token",
         token, "--output", output, "--fps", "4", "--frame-interval", "5", "--max-rate", "10",
         "--max-age", "30", "--log", str(log)], cwd=tmp_path, capture_output=True, text=True,
        timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    records = [json.loads(line) for line in log.read_text().splitlines()]
    poses = _server_poses(live_server, session_id)
    with Client(live_server, admin_key=ADMIN_KEY) as vloc:
        origin = vloc.get_map(map_id).origin
    kind = {"vision": "VISION_POSITION_ESTIMATE", "odometry": "ODOMETRY"}[output]
    got = autopilot.received(kind)
    estimates: list[ExternalNav] = autopilot.external_nav()
    # the origin came first (once: the link never dropped), and it is the map's own
    origins = autopilot.received("SET_GPS_GLOBAL_ORIGIN")
    assert len(origins) == 1 and origins[0].at < got[0].at and len(estimates) == len(got)
    assert abs(origins[0].fields["latitude"] / 1e7 - origin.lat) <= 2e-7
    assert abs(origins[0].fields["longitude"] / 1e7 - origin.lon) <= 2e-7
    sent = {r["sent"]["usec" if output == "vision" else "time_usec"]: r for r in records
            if "sent" in r}
    assert len(sent) == len(estimates) >= 3, [r.get("why") for r in records]
    resets, counter, tracked, gap = {}, 0, False, False
    for r in records:
        if r.get("status") == "tracking":
            counter += tracked and gap  # lost, then found again: the local frame jumped
            resets[r["seq"]] = counter
            tracked, gap = True, False
        elif r.get("status") is not None:
            gap = tracked
    errors = []
    for est in estimates:
        record = sent[est.usec]
        pose = poses[record["seq"]]
        assert pose.status == "tracking"
        # where the autopilot puts it is where the service put it (float32 metres)
        e, n = GeoOrigin(pose.lat, pose.lon).to_local([est.lat], [est.lon])
        assert math.hypot(e[0], n[0]) < 0.05
        assert (est.north, est.east) == pytest.approx((pose.y, pose.x), abs=1e-3)
        nn, ne, ee = est.cov_ne
        assert horizontal_accuracy([ee, ne, ne, nn]) == pytest.approx(
            pose.horizontal_accuracy_m, rel=1e-5)
        if output == "vision":  # ArduPilot's one noise: the horizontal spread, no NaN
            assert est.pos_err_m == pytest.approx(math.sqrt(nn + ee), rel=1e-6)
            assert math.isfinite(est.ang_err_rad)
        assert est.reset_counter == resets[record["seq"]]
        shot = truth[record["frame"]]
        e, n = GeoOrigin(shot.lat, shot.lon).to_local([est.lat], [est.lon])
        errors.append(math.hypot(e[0], n[0]))
    assert sorted(errors)[len(errors) // 2] < 10.0, errors
    for r in records:
        if r.get("status") in ("initialising", "lost"):
            assert "sent" not in r


# -- a camera: OpenCV's capture ----------------------------------------------------------

@pytest.mark.parametrize(("source", "opened"), [
    ("0", 0), ("2", 2), ("/dev/video0", "/dev/video0"), ("rtsp://10.0.0.5:8554/cam", None),
    ("http://10.0.0.5:8080/video.mjpg", None), ("flight.avi", None)])
def test_a_camera_index_opens_the_device_and_anything_else_is_a_path_or_url(
        source, opened, monkeypatch):
    assert capture_source(source) == (source if opened is None else opened)
    # the argument OpenCV is given, through the camera the bridge opens
    import cv2

    asked = []

    class LiveCapture:  # a live device: no length, frames as fast as it delivers them
        def __init__(self, arg):
            asked.append(arg)

        def isOpened(self):  # noqa: N802 (OpenCV's name)
            return True

        def get(self, prop):
            return {cv2.CAP_PROP_FPS: 30.0, cv2.CAP_PROP_FRAME_COUNT: -1.0}[prop]

        def read(self):
            return False, None

        def release(self):
            pass

    monkeypatch.setattr(cv2, "VideoCapture", LiveCapture)
    camera = Camera(source)
    assert camera.latest(timeout=5.0) is None and camera.period is None
    camera.close()
    assert asked == [capture_source(source)]


def test_the_command_line_takes_a_device_index_and_a_token_that_starts_with_a_dash():
    from vloc.clients.sdk.mavlink import _attached, parser

    # one token in 64 starts with "-" (URL-safe base64)
    argv = ["0", "--mavlink", "udpout:127.0.0.1:14550", "--session", "s1", "--token",
            "-Zx3_k", "--admin-key", "--k"]
    args = parser().parse_args(_attached(argv))
    assert (args.token, args.admin_key, args.session) == ("-Zx3_k", "--k", "s1")
    assert capture_source(args.source) == 0
    with pytest.raises(SystemExit):  # what argparse makes of it unattached
        parser().parse_args(argv)


VIDEO_FPS, HOLD = 8.0, 8
"""The flight as a video: each query shot held for HOLD frames (1 s at VIDEO_FPS)."""


def _video(path: Path, shots) -> Path:
    import cv2
    import numpy as np

    out = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), VIDEO_FPS, (320, 240))
    assert out.isOpened()
    for s in shots:
        image = cv2.imdecode(np.frombuffer(s.jpeg, np.uint8), cv2.IMREAD_COLOR)
        for _ in range(HOLD):
            out.write(image)
    out.release()
    return path


def test_vloc_mavlink_samples_a_video_at_the_chosen_rate(live_server, flight, shots,
                                                          autopilot, tmp_path):
    """A video file goes through OpenCV's capture as a stream URL does: played at its own
    frame rate, sampled at --fps, the newest frame each time; each pose that reaches the
    autopilot is where the frame it was sent for shows."""
    from vloc.workers.core.geo import GeoOrigin

    map_id, _ = flight
    _, queries = shots
    video = _video(tmp_path / "flight.avi", queries)
    session_id, token = _session(live_server, map_id)
    log = tmp_path / "bridge.jsonl"
    fps = 2.0
    run = subprocess.run(
        [sys.executable, "-m", "vloc.clients.cli", "mavlink", str(video), "--mavlink",
         autopilot.address, "--server", live_server, "--session", session_id, "--token",
         token, "--fps", str(fps), "--max-rate", "10", "--max-age", "30", "--log",
         str(log)], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    records = [json.loads(line) for line in log.read_text().splitlines()]
    numbers = [int(r["frame"].removeprefix("frame-")) for r in records]
    length_s = len(queries) * HOLD / VIDEO_FPS
    # the newest frame each time, never one twice, at --fps at most over the video's length
    assert numbers == sorted(set(numbers)) and 4 <= len(numbers) <= length_s * fps + 2
    steps = sorted(b - a for a, b in zip(numbers, numbers[1:], strict=False))
    assert steps[len(steps) // 2] >= VIDEO_FPS / fps - 1
    shown = [(n - 1) // HOLD for n in numbers]
    assert len(set(shown)) >= 4, numbers  # it went through the video, not one part of it
    poses = _server_poses(live_server, session_id)
    pairs = check_messages(autopilot, records, poses)
    assert len(pairs) >= 2, [r.get("why") for r in records]
    shot_of = {r["seq"]: queries[(int(r["frame"][6:]) - 1) // HOLD] for r in records
               if "seq" in r}
    errors = []
    for msg, pose in pairs:
        truth = shot_of[pose.seq]
        e, n = GeoOrigin(truth.lat, truth.lon).to_local([msg.fields["lat"] / 1e7],
                                                        [msg.fields["lon"] / 1e7])
        errors.append(math.hypot(e[0], n[0]))
    # nearer the shot its frame shows than the shots are to each other (20 m)
    assert sorted(errors)[len(errors) // 2] < 20.0, errors


def test_without_pymavlink_the_command_names_the_extra(tmp_path):
    script = ("import sys; sys.modules['pymavlink'] = None\n"
              "from vloc.clients.cli import main\n"
              "main(['mavlink', '.', '--mavlink', 'udpout:127.0.0.1:9', '--session', 's'])")
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         timeout=60, cwd=tmp_path)
    assert run.returncode == 2
    assert "pymavlink" in run.stderr and "vloc[mavlink]" in run.stderr


def test_the_light_client_installs_with_the_mavlink_extra(tmp_path):
    import shutil

    source = tmp_path / "src"
    shutil.copytree(REPO_ROOT / "clients" / "sdk", source,
                    ignore=shutil.ignore_patterns("__pycache__", "*.egg-info", "build"))
    env_dir = tmp_path / "venv"
    pip = bare_environment(env_dir)
    py = str(env_dir / "bin" / "python")
    out = subprocess.run([*pip, "install", "--quiet", f"{source}[mavlink]"],
                         capture_output=True, text=True, timeout=600)
    if out.returncode and ("No matching distribution" in out.stderr
                           or "connection" in out.stderr.lower()):
        if os.environ.get("VLOC_REQUIRE_SERVICES") == "1":
            pytest.fail(out.stderr[-500:])
        pytest.skip("the package index is unreachable: " + out.stderr[-500:])
    assert out.returncode == 0, out.stdout + out.stderr
    check = subprocess.run(
        [py, "-c", "import pymavlink, vloc_client.mavlink as m; print(m.Bridge.__name__)"],
        capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert check.returncode == 0 and check.stdout.strip() == "Bridge", check.stderr
    helped = subprocess.run([str(env_dir / "bin" / "vloc-mavlink"), "--help"],
                            capture_output=True, text=True, timeout=120)
    assert helped.returncode == 0 and "GPS_INPUT" in helped.stdout
    frozen = subprocess.run([*pip, "freeze"], capture_output=True, text=True)
    assert "opencv" not in frozen.stdout.lower() and "numpy" not in frozen.stdout.lower()


# -- a real flight: seneca-uav ---------------------------------------------------------------

LEG = [f"IMG_{n:04d}.jpg" for n in range(548, 558)]
"""A straight leg of pass 2 (bearing about 55 degrees, 5 s between images)."""
LEG_HEADING, LEG_ALTITUDE, LEG_VELOCITY = 55.0, 282.0, (4.7, 3.3)
DOCS = REPO_ROOT / "docs" / "devices"


def _seneca_truth(seneca_dir: Path) -> dict[str, dict]:
    with open(seneca_dir / "ground_truth.csv", newline="") as fh:
        return {r["filename"]: r for r in csv.DictReader(fh)}


def _near_leg(truth: dict[str, dict], radius_m: float = 40.0) -> list[str]:
    """The pass-1 images within ``radius_m`` of the leg: a small map that covers it."""
    from vloc.workers.core.geo import GeoOrigin

    leg = [truth[n] for n in LEG]
    origin = GeoOrigin(float(leg[0]["lat"]), float(leg[0]["lon"]), 0.0)

    def en(rows):
        e, n = origin.to_local([float(r["lat"]) for r in rows], [float(r["lon"]) for r in rows])
        return list(zip(e, n, strict=True))

    ours = en(leg)
    return [r["filename"] for r, p in zip(truth.values(), en(list(truth.values())), strict=True)
            if r["pass"] == "1" and min(math.dist(p, q) for q in ours) < radius_m]


@pytest.mark.dataset
def test_a_seneca_leg_reaches_the_autopilot_as_its_poses(live_server, seneca_dir, autopilot,
                                                          tmp_path):
    truth = _seneca_truth(seneca_dir)
    images = seneca_dir / "images"
    with Client(live_server, admin_key=ADMIN_KEY) as vloc:
        m = vloc.create_map("seneca leg")
        vloc.upload_images(m.id, [images / n for n in _near_leg(truth)])
        vloc.wait_for_job(vloc.build_map(m.id).id, timeout=600)
        s = vloc.create_session(m.id, seed=5)
    folder = tmp_path / "leg"
    folder.mkdir()
    for n in LEG:
        (folder / n).write_bytes((images / n).read_bytes())
    autopilot.state.heading_deg, autopilot.state.altitude_m = LEG_HEADING, LEG_ALTITUDE
    autopilot.state.velocity_en = LEG_VELOCITY
    log = tmp_path / "bridge.jsonl"
    run = subprocess.run(
        [sys.executable, "-m", "vloc.clients.cli", "mavlink", str(folder), "--mavlink",
         autopilot.address, "--server", live_server, "--session", s.id, "--token", s.token,
         "--fps", "1", "--frame-interval", "5", "--max-age", "30", "--log", str(log)],
        cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    records = [json.loads(line) for line in log.read_text().splitlines()]
    poses = _server_poses(live_server, s.id)
    pairs = check_messages(autopilot, records, poses)
    tracking = [p for p in poses.values() if p.status == "tracking"]
    assert len(pairs) == len(tracking) >= 5
    assert all(p.altitude_m == LEG_ALTITUDE for p in poses.values())
    assert all(r["metadata"]["heading_deg"] == pytest.approx(LEG_HEADING) for r in records)
    # against the truth: what the autopilot was told, and what it was told of its accuracy
    from vloc.workers.core.geo import GeoOrigin

    frame_of = {r["seq"]: r["frame"] for r in records if "seq" in r}
    errors = []
    for msg, pose in pairs:
        t = truth[frame_of[pose.seq]]
        origin = GeoOrigin(float(t["lat"]), float(t["lon"]), 0.0)
        e, n = origin.to_local([msg.fields["lat"] / 1e7], [msg.fields["lon"] / 1e7])
        errors.append(math.hypot(e[0], n[0]))
    print(f"seneca leg: {len(pairs)} GPS_INPUT of {len(poses)} frames; error to the truth "
          f"median {sorted(errors)[len(errors) // 2]:.1f} m, max {max(errors):.1f} m")
    assert sorted(errors)[len(errors) // 2] < 25.0
    if os.environ.get("VLOC_WRITE_SCREENSHOTS") == "1":
        _plot_leg(pairs, truth, frame_of, DOCS / "mavlink-seneca.png")


def _plot_leg(pairs, truth, frame_of, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from vloc.workers.core.geo import GeoOrigin

    first = truth[LEG[0]]
    origin = GeoOrigin(float(first["lat"]), float(first["lon"]), 0.0)
    te, tn = origin.to_local([float(truth[n]["lat"]) for n in LEG],
                             [float(truth[n]["lon"]) for n in LEG])
    me, mn = origin.to_local([m.fields["lat"] / 1e7 for m, _ in pairs],
                             [m.fields["lon"] / 1e7 for m, _ in pairs])
    fig, ax = plt.subplots(figsize=(5.2, 4.0), dpi=80)
    ax.plot(te, tn, "k.-", lw=1, label="GPS of the images (truth)")
    for (msg, _), x, y in zip(pairs, me, mn, strict=True):
        ax.add_patch(plt.Circle((x, y), msg.fields["horiz_accuracy"], color="tab:red",
                                alpha=0.12, lw=0))
    ax.plot(me, mn, "o", color="tab:red", ms=4, label="GPS_INPUT the autopilot got")
    ax.set_aspect("equal")
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.set_title("seneca-uav, one leg through vloc mavlink", fontsize=10)
    ax.legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
