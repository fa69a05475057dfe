"""Teach and repeat in the robot world: a taught drive with wheel odometry, and a camera
that renders whatever pose a simulated robot reaches on the repeat.

The taught drive is one pass of the street world's robot (Weiss et al. 2008: 0.6 m between
frames, a forward camera 1 m above the ground), optionally a little further than one round
so that its end sees its start again (one loop to close). Its wheel odometry integrates the
true motion with a scale error and a heading bias chosen so that, at the end of the drive,
odometry is off by a given share of the distance driven.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import datetime, timedelta

import numpy as np

from vloc.clients.world import robot
from vloc.clients.world.camera import Camera, Pose
from vloc.clients.world.lighting import AutoExposure, camera_response, illumination_for_pass
from vloc.clients.world.passes import prepare_pass
from vloc.clients.world.writer import DEFAULT_ORIGIN, FIRST_DAY
from vloc.workers.core.exif import encode_jpeg_with_gps
from vloc.workers.core.geo import GeoOrigin


@dataclass
class TaughtDrive:
    """One taught drive.

    Attributes
    ----------
    names : list of str
        File names, in driving order.
    jpegs : list of bytes
        The frames, EXIF-tagged with the true position plus GPS noise.
    poses : (N, 3) float ndarray
        True ``(east, north, yaw)`` of each frame in the world's frame.
    odometry : (N, 3) float ndarray
        What the wheels said, starting at the true first pose.
    """

    names: list[str]
    jpegs: list[bytes]
    poses: np.ndarray
    odometry: np.ndarray


class RobotCamera:
    """The street world rendered from any robot pose under one illumination."""

    def __init__(self, scene, light: str, rng: np.random.Generator, *,
                 supersample: int = 1) -> None:
        self.illum = illumination_for_pass(light, rng)
        self.renderer, _ = prepare_pass(scene, self.illum, Camera(), rng, supersample=supersample)
        self.exposure = AutoExposure(self.illum)
        self.rng = rng

    def frame(self, x: float, y: float, yaw: float) -> np.ndarray:
        """(240, 320, 3) uint8 BGR frame of a robot at ``(x, y)`` heading ``yaw``."""
        pose = Pose(np.array([x, y, robot.CAMERA_HEIGHT]), float(yaw))
        radiance = self.renderer.render(pose)
        return camera_response(radiance, self.illum, self.rng, self.exposure(radiance))


class TeachWorld:
    """The street world of ``seed`` with a loop of ``route_length`` metres.

    Parameters
    ----------
    seed : int
    route_length : float
        Perimeter of the loop (metres, at least 24).
    origin : GeoOrigin
        Where the world's frame lies on the Earth.
    """

    def __init__(self, seed: int, route_length: float, *,
                 origin: GeoOrigin = DEFAULT_ORIGIN) -> None:
        self.seed = seed
        self.origin = origin
        scene_rng, self._drive_rng, self._camera_rng = np.random.default_rng(seed).spawn(3)
        self.scene, self.route = robot.street_world(scene_rng, route_length)

    def camera(self, light: str, *, stream: int = 0) -> RobotCamera:
        """A camera under ``light``; ``stream`` picks independent sensor noise."""
        return RobotCamera(self.scene, light, self._camera_rng.spawn(stream + 1)[-1])

    def teach(self, *, light: str = "sunny", extra_m: float = 0.0, spacing: float = robot.SPACING,
              drift: float = 0.05, gps_noise_m: float = 0.5, quality: int = 90) -> TaughtDrive:
        """Drive the loop once (and ``extra_m`` further), rendering and tagging each frame.

        ``drift`` is the odometry's error at the end of the drive as a share of the distance
        driven.
        """
        rng = self._drive_rng
        frames = int(round((self.route.length + extra_m) / spacing))
        cam_poses = robot.robot_poses(self.route, rng, frames=frames, spacing=spacing)
        poses = np.array([[p.position[0], p.position[1], p.yaw] for p in cam_poses])
        camera = RobotCamera(self.scene, light, rng)
        noise = rng.normal(0.0, gps_noise_m, (frames, 2)) if gps_noise_m > 0 else \
            np.zeros((frames, 2))
        names, jpegs = [], []
        start = FIRST_DAY + timedelta(hours=12)
        for k, pose in enumerate(cam_poses):
            radiance = camera.renderer.render(pose)
            image = camera_response(radiance, camera.illum, rng, camera.exposure(radiance))
            lat, lon = (float(v) for v in self.origin.to_wgs84(poses[k, 0] + noise[k, 0],
                                                                poses[k, 1] + noise[k, 1]))
            names.append(f"taught_{k:05d}.jpg")
            jpegs.append(encode_jpeg_with_gps(image, quality=quality, lat=lat, lon=lon,
                                              alt=self.origin.alt + robot.CAMERA_HEIGHT,
                                              captured_at=_at(start, k)))
        return TaughtDrive(names, jpegs, poses, drifting_odometry(poses, rng, drift))


def _at(start: datetime, k: int) -> datetime:
    return start + timedelta(seconds=k)


def integrate(poses: np.ndarray, scale: float, bias_per_m: float,
              noise: np.ndarray) -> np.ndarray:
    """Odometry from true poses: each step's length times ``scale`` and its turn plus
    ``bias_per_m`` per metre and ``noise`` (radians, one per step)."""
    out = np.empty_like(poses)
    out[0] = poses[0]
    for k in range(1, len(poses)):
        d = float(np.hypot(*(poses[k, :2] - poses[k - 1, :2])))
        turn = math.remainder(poses[k, 2] - poses[k - 1, 2], 2 * math.pi)
        th = out[k - 1, 2] + turn + bias_per_m * d + noise[k]
        mid = out[k - 1, 2] + 0.5 * (th - out[k - 1, 2])
        out[k] = (out[k - 1, 0] + scale * d * math.cos(mid),
                  out[k - 1, 1] + scale * d * math.sin(mid), th)
    return out


def drifting_odometry(poses: np.ndarray, rng: np.random.Generator, drift: float, *,
                      heading_noise_deg: float = 0.02) -> np.ndarray:
    """Odometry whose final position is off by ``drift`` times the distance driven: a 1 %
    scale error, heading noise of ``heading_noise_deg`` per step (a random walk), and the
    heading bias (found by bisection) that makes up the rest."""
    length = float(np.sum(np.hypot(*np.diff(poses[:, :2], axis=0).T)))
    noise = rng.normal(0.0, math.radians(heading_noise_deg), len(poses))
    target = drift * length

    def error(bias: float) -> float:
        odo = integrate(poses, 1.01, bias, noise)
        return float(np.hypot(*(odo[-1, :2] - poses[-1, :2])))

    # at most 60 degrees of heading drift in all: beyond that the end error stops growing
    lo, hi = 0.0, math.radians(60.0) / max(length, 1.0)
    if error(lo) >= target:
        return integrate(poses, 1.01, 0.0, noise)
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if error(mid) < target else (lo, mid)
    return integrate(poses, 1.01, 0.5 * (lo + hi), noise)


def odometry_csv(names: list[str], odometry: np.ndarray) -> bytes:
    """The odometry CSV the service takes (``filename, x, y, theta``)."""
    lines = ["filename,x,y,theta"]
    lines += [f"{n},{x:.4f},{y:.4f},{th:.6f}" for n, (x, y, th) in zip(names, odometry,
                                                                        strict=True)]
    return ("\n".join(lines) + "\n").encode()
