"""Generating a world and writing it as a data set folder.

Layout (the one :func:`workers.core.evaluation.datasets.load_dataset` and ``vloc eval`` read)::

    OUT/images/p1_00000.jpg ...   320x240 JPEGs with EXIF GPS position and capture time
    OUT/ground_truth.csv          filename,pass,captured_at,lat,lon,alt_m (true positions)
    OUT/exif_gps.csv              filename,pass,lat,lon,alt_m (what each image's EXIF says)
    OUT/poses.csv                 filename,pass,east_m,north_m,up_m,heading_deg,pitch_deg,roll_deg
    OUT/world.json                parameters, for reproducing the world

Pass 1 is the mapping pass: as in real mapping runs, its images are tagged by a noisy GPS,
the true position plus independent Gaussian noise of ``gps_noise_m`` per axis and frame.
The other passes are query passes; their EXIF carries the true position (an evaluation
ignores it, and a test can compare it with the estimate). ``ground_truth.csv`` always holds
the true positions.

Everything is drawn from ``numpy.random.default_rng(seed)`` through independent child
streams (scene, GPS noise, one per pass), and no clock is read, so the same arguments
give byte-identical files.
"""

from __future__ import annotations

import csv
import json
import time
from dataclasses import dataclass, field
from datetime import datetime, timedelta
from pathlib import Path

import numpy as np

from vloc.clients.world import robot, uav
from vloc.clients.world.camera import Camera
from vloc.clients.world.lighting import ILLUMINATIONS, illumination_for_pass
from vloc.clients.world.passes import prepare_pass, render_frames
from vloc.workers.core.exif import encode_jpeg_with_gps
from vloc.workers.core.geo import GeoOrigin

KINDS: tuple[str, ...] = ("robot", "uav")
DEFAULT_ORIGIN = GeoOrigin(48.5363, 9.0578, 340.0)
"""Tuebingen, where Weiss et al. recorded their rounds."""
FIRST_DAY = datetime(2013, 6, 4)
FRAME_INTERVAL_S = 1.0
"""One frame per second, as the robot of Weiss et al."""
GPS_NOISE_M = {"robot": 0.5, "uav": 2.0}
"""Default GPS noise: a differential GPS on the robot (Weiss et al.: below 0.5 m under
ideal conditions), a plain GPS receiver on the quadcopter."""


@dataclass(frozen=True)
class WorldInfo:
    """What :func:`generate_world` wrote.

    Attributes
    ----------
    out_dir : Path
    kind : str
    seed : int
    passes : tuple of str
        Illumination of each pass, pass 1 first.
    frames_per_pass : int
    route_length_m : float
    frame_spacing_m : float
        Mean distance between consecutive frames along the route.
    gps_noise_m : float
        Sigma of the GPS noise in the mapping pass's EXIF.
    images : int
    timings : dict of str -> float
        Seconds spent building the scene, shading, rendering and writing (not written to
        disk: files stay deterministic).
    """

    out_dir: Path
    kind: str
    seed: int
    passes: tuple[str, ...]
    frames_per_pass: int
    route_length_m: float
    frame_spacing_m: float
    gps_noise_m: float
    images: int
    timings: dict[str, float] = field(default_factory=dict)

    @property
    def ground_truth(self) -> Path:
        return self.out_dir / "ground_truth.csv"

    @property
    def image_dir(self) -> Path:
        return self.out_dir / "images"


def generate_world(out_dir: str | Path, *, kind: str = "robot", seed: int = 0,
                   passes: tuple[str, ...] | list[str] = ("sunny", "cloudy", "dusk"),
                   frames: int | None = None, route_length: float | None = None,
                   gps_noise_m: float | None = None, quality: int = 90,
                   origin: GeoOrigin = DEFAULT_ORIGIN, supersample: int = 2,
                   altitude: float | None = None, pitch_deg: float | None = None,
                   relief_m: float = 0.0, altitude_drift_m: float = 0.0,
                   overwrite: bool = False, progress=None) -> WorldInfo:
    """Generate a world from a seed and render a route through it once per pass.

    Parameters
    ----------
    out_dir : path
        Output folder (created).
    kind : {"robot", "uav"}
        Street world seen by a ground robot (Weiss et al. 2008) or terrain seen by a
        quadcopter (Erhard et al., Flyphone).
    seed : int
    passes : sequence of str
        Illumination of each traversal: ``sunny``, ``cloudy`` or ``dusk``.
    frames : int, optional
        Frames per pass. Alone, it sets the route length (``frames`` times the kind's
        frame spacing: 0.6 m for the robot); with ``route_length`` it sets the stride.
    route_length : float, optional
        Metres: the perimeter of the robot's loop (default 260) or the length of the
        UAV's survey path (default 600).
    gps_noise_m : float, optional
        Sigma of the mapping pass's GPS noise per axis; 0.5 m (robot) or 2 m (UAV).
    quality : int
        JPEG quality.
    origin : GeoOrigin
        Geographic position of the world's local frame.
    supersample : int
        Render at this multiple of 320x240 and average down (anti-aliasing).
    altitude, pitch_deg : float, optional
        UAV only: mean flight altitude above ground (default 25 m, 5 to 100) and camera
        pitch (default -90, straight down; 0 looks ahead).
    relief_m : float
        UAV only: hills, this high from valley to hilltop (0: flat land).
    altitude_drift_m : float
        Every pass's EXIF altitudes drift from the truth by this much, growing evenly from
        its first frame to its last, as a consumer GPS's altitude wanders in flight; the
        ground truth keeps the true altitudes.
    overwrite : bool
        Replace the images of an earlier world in ``out_dir``; otherwise refuse.
    progress : callable, optional
        ``progress(done, total)`` after each frame.

    Returns
    -------
    WorldInfo
    """
    passes = tuple(passes)
    _check(kind, passes, frames, route_length, gps_noise_m, quality, supersample, altitude)
    if relief_m and kind != "uav":
        raise ValueError("relief_m applies to the UAV world only")
    if not (0.0 <= float(relief_m) <= 200.0 and abs(float(altitude_drift_m)) <= 1000.0):
        raise ValueError(f"relief_m must be within 0..200 m and altitude_drift_m within "
                         f"+-1000 m, got {relief_m} and {altitude_drift_m}")
    out_dir = Path(out_dir)
    image_dir = out_dir / "images"
    _prepare_folder(image_dir, overwrite)
    spacing, length, frames = _sizes(kind, frames, route_length, altitude)
    gps_sigma = GPS_NOISE_M[kind] if gps_noise_m is None else float(gps_noise_m)
    scene_rng, gps_rng, pass_parent = np.random.default_rng(seed).spawn(3)
    pass_rngs = pass_parent.spawn(len(passes))
    timings = {"scene": 0.0, "shading": 0.0, "rendering": 0.0, "writing": 0.0}
    t = time.perf_counter()
    if kind == "robot":
        scene, route = robot.street_world(scene_rng, length)
        options = {}
    else:
        options = {"altitude": uav.ALTITUDE if altitude is None else float(altitude),
                   "pitch_deg": uav.PITCH_DEG if pitch_deg is None else float(pitch_deg)}
        scene, route = uav.terrain_world(scene_rng, length, options["altitude"],
                                         options["pitch_deg"], relief_m=float(relief_m))
    timings["scene"] = time.perf_counter() - t
    camera = Camera()
    gps_noise = gps_rng.normal(0.0, gps_sigma, (frames, 2)) if gps_sigma > 0 else np.zeros((frames, 2))
    truth_rows, exif_rows, pose_rows, pass_meta = [], [], [], []
    clock = {}
    total = frames * len(passes)
    for index, (name, rng) in enumerate(zip(passes, pass_rngs, strict=True)):
        illum = illumination_for_pass(name, rng)
        if kind == "robot":
            poses = robot.robot_poses(route, rng, frames=frames, spacing=spacing)
        else:
            poses = uav.uav_poses(route, rng, frames=frames, spacing=spacing,
                                  relief_m=float(relief_m), **options)
        t = time.perf_counter()
        renderer, absent = prepare_pass(scene, illum, camera, rng, supersample=supersample)
        timings["shading"] += time.perf_counter() - t
        start = clock.get(name, FIRST_DAY + timedelta(days=illum.day_offset)
                          + _time_of_day(illum.time))
        noise = gps_noise if index == 0 else np.zeros((frames, 2))
        loop_start, writing = time.perf_counter(), 0.0
        for k, image in enumerate(render_frames(renderer, poses, illum, rng)):
            t = time.perf_counter()
            pose = poses[k]
            captured = start + timedelta(seconds=k * FRAME_INTERVAL_S)
            filename = f"p{index + 1}_{k:05d}.jpg"
            e, n, up = (float(v) for v in pose.position)
            lat, lon = (float(v) for v in origin.to_wgs84(e, n))
            tag_lat, tag_lon = (float(v) for v in origin.to_wgs84(e + noise[k, 0], n + noise[k, 1]))
            alt = origin.alt + up
            tag_alt = alt + altitude_drift_m * k / max(frames - 1, 1)
            data = encode_jpeg_with_gps(image, quality=quality, lat=tag_lat, lon=tag_lon,
                                        alt=tag_alt, captured_at=captured)
            (image_dir / filename).write_bytes(data)
            truth_rows.append([filename, index + 1, _iso(captured), f"{lat:.9f}", f"{lon:.9f}", f"{alt:.3f}"])
            exif_rows.append([filename, index + 1, f"{tag_lat:.9f}", f"{tag_lon:.9f}",
                              f"{tag_alt:.3f}"])
            pose_rows.append([filename, index + 1, f"{e:.4f}", f"{n:.4f}", f"{up:.4f}",
                              f"{pose.heading_deg:.3f}", f"{np.degrees(pose.pitch):.3f}",
                              f"{np.degrees(pose.roll):.3f}"])
            writing += time.perf_counter() - t
            if progress is not None:
                progress(index * frames + k + 1, total)
        timings["writing"] += writing
        timings["rendering"] += time.perf_counter() - loop_start - writing
        clock[name] = start + timedelta(seconds=frames * FRAME_INTERVAL_S + 120.0)
        pass_meta.append({
            "pass": index + 1, "illumination": name,
            "role": "map" if index == 0 else "query",
            "exif_gps": (f"true position + Gaussian noise, sigma {gps_sigma:g} m per axis"
                         if index == 0 else "true position"),
            "first_frame_at": _iso(start), "frames": frames, "parked_cars_absent": len(absent),
            "lighting": illum.to_json()})
    _write_csv(out_dir / "ground_truth.csv",
               ["filename", "pass", "captured_at", "lat", "lon", "alt_m"], truth_rows)
    _write_csv(out_dir / "exif_gps.csv", ["filename", "pass", "lat", "lon", "alt_m"], exif_rows)
    _write_csv(out_dir / "poses.csv", ["filename", "pass", "east_m", "north_m", "up_m",
                                       "heading_deg", "pitch_deg", "roll_deg"], pose_rows)
    meta = {
        "generator": "vloc world", "format": 1, "kind": kind, "seed": seed,
        "origin": {"lat": origin.lat, "lon": origin.lon, "alt_m": origin.alt,
                   "frame": "local east-north-up tangent plane at the origin"},
        "camera": {"width": camera.width, "height": camera.height, "hfov_deg": camera.hfov_deg,
                   "focal_px": round(camera.focal, 6), "supersample": supersample, **options},
        "route": {"shape": ("closed loop round a block" if kind == "robot" else
                            "loop" if route.closed else "lawnmower survey"),
                  "length_m": round(route.length, 3), "closed": route.closed},
        "frames_per_pass": frames, "frame_spacing_m": round(spacing, 6),
        "frame_interval_s": FRAME_INTERVAL_S, "jpeg_quality": quality,
        "gps_noise": {"sigma_m": gps_sigma, "pass": 1,
                      "model": "independent Gaussian per axis and frame",
                      "exif_positions": "exif_gps.csv",
                      "note": "pass 1 (map) EXIF = truth + noise; other passes' EXIF = truth; "
                              "ground_truth.csv = truth"},
        "terrain": {"relief_m": float(relief_m),
                    "altitude_drift_m": float(altitude_drift_m),
                    "note": "EXIF altitudes drift from the truth evenly over each pass"},
        "passes": pass_meta,
    }
    (out_dir / "world.json").write_text(json.dumps(meta, indent=2) + "\n", encoding="utf-8")
    return WorldInfo(out_dir=out_dir, kind=kind, seed=seed, passes=passes,
                     frames_per_pass=frames, route_length_m=float(route.length),
                     frame_spacing_m=spacing, gps_noise_m=gps_sigma,
                     images=len(truth_rows), timings=timings)


def _sizes(kind: str, frames: int | None, route_length: float | None,
           altitude: float | None) -> tuple[float, float, int]:
    """(frame spacing, route length, frames per pass) from what the caller fixed.

    ``frames`` alone gives a route of ``frames`` times the kind's spacing, but never
    shorter than the kind's shortest route; then the frames spread out over it.
    """
    if kind == "robot":
        spacing, default_length, shortest = robot.SPACING, robot.ROUTE_LENGTH, robot.MIN_ROUTE
    else:
        spacing, default_length = uav.SPACING, uav.ROUTE_LENGTH
        shortest = uav.shortest_route(uav.ALTITUDE if altitude is None else altitude)
    if frames is None:
        length = default_length if route_length is None else float(route_length)
        return spacing, length, max(2, int(round(length / spacing)))
    length = max(frames * spacing, shortest) if route_length is None else float(route_length)
    return length / frames, length, frames


def _check(kind, passes, frames, route_length, gps_noise_m, quality, supersample, altitude) -> None:
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    if not passes:
        raise ValueError("at least one pass is needed")
    unknown = [p for p in passes if p not in ILLUMINATIONS]
    if unknown:
        raise ValueError(f"unknown illumination {unknown[0]!r}; choose from {sorted(ILLUMINATIONS)}")
    if frames is not None and int(frames) < 2:
        raise ValueError(f"frames must be at least 2, got {frames}")
    if route_length is not None and not float(route_length) > 0:
        raise ValueError(f"route_length must be positive, got {route_length}")
    if gps_noise_m is not None and not float(gps_noise_m) >= 0:
        raise ValueError(f"gps_noise_m must be zero or positive, got {gps_noise_m}")
    if not 1 <= int(quality) <= 100:
        raise ValueError(f"quality must be within 1..100, got {quality}")
    if not 1 <= int(supersample) <= 4:
        raise ValueError(f"supersample must be within 1..4, got {supersample}")
    if altitude is not None and not 5.0 <= float(altitude) <= 100.0:
        raise ValueError(f"altitude must be within 5..100 m, got {altitude}")


def _prepare_folder(image_dir: Path, overwrite: bool) -> None:
    if image_dir.is_dir() and any(image_dir.glob("*.jpg")):
        if not overwrite:
            raise FileExistsError(f"{image_dir} already holds images; pass overwrite=True "
                                  "(--overwrite) to replace them")
        for old in image_dir.glob("*.jpg"):
            old.unlink()
    image_dir.mkdir(parents=True, exist_ok=True)


def _time_of_day(hms: str) -> timedelta:
    h, m, s = (int(v) for v in hms.split(":"))
    return timedelta(hours=h, minutes=m, seconds=s)


def _iso(t: datetime) -> str:
    return t.strftime("%Y-%m-%dT%H:%M:%S.") + f"{t.microsecond // 1000:03d}"


def _write_csv(path: Path, header: list[str], rows: list[list]) -> None:
    with path.open("w", newline="", encoding="utf-8") as f:
        writer = csv.writer(f, lineterminator="\n")
        writer.writerow(header)
        writer.writerows(rows)


