"""The UAV world of Flyphone (Erhard et al., section 5.1).

A quadcopter flies a survey over open land: fields, meadows, farm yards with buildings,
orchards, woods, ponds, roads and tracks. The camera looks straight down by default
(``pitch_deg=-90``) from 5 to 100 m; a forward-looking camera (pitch above -45 degrees)
flies a loop instead, as Flyphone's phone did round its courtyard at 5 to 10 m. Frames
are further apart than the robot's and unevenly so ("the distances between images vary
because of gusts of wind"), each pass flies a few metres off the others at a slightly
different altitude, and the camera's yaw differs between passes.
"""

from __future__ import annotations

import math

import numpy as np

from vloc.clients.world.camera import Pose
from vloc.clients.world.objects import add_building, add_car, add_tree
from vloc.clients.world.routes import Route, follow, lawnmower, rounded_rectangle, smooth_noise
from vloc.clients.world.scene import Scene, ground_plane
from vloc.clients.world.terrain import parcels, terrain_ground

ALTITUDE = 25.0
PITCH_DEG = -90.0
SPACING = 3.0
"""Mean metres between frames: 3 m/s at one frame per second."""
ROUTE_LENGTH = 600.0
HFOV_DEG = 60.0


def footprint_width(altitude: float) -> float:
    """Ground width seen across the image by a nadir camera at ``altitude``."""
    return 2.0 * altitude * math.tan(math.radians(HFOV_DEG) / 2.0)


def shortest_route(altitude: float) -> float:
    """Length of the shortest survey: two lanes, each one lane spacing long."""
    lane = 0.6 * footprint_width(altitude)
    return 2 * lane + math.pi * lane / 2 + 1.0


def survey_route(route_length: float, altitude: float, pitch_deg: float) -> Route:
    """A lawnmower path whose lanes overlap by 40 % (nadir camera), or a loop (camera
    looking ahead), about ``route_length`` metres long, centred on the origin."""
    if pitch_deg > -45.0:
        half = route_length / 8.0
        r = rounded_rectangle(half * 1.25, half * 0.75, min(10.0, half / 3))
        return r
    lane = 0.6 * footprint_width(altitude)
    best = None
    for n in range(2, 40):
        width = (route_length - (n - 1) * math.pi * lane / 2) / n
        if width < lane:
            break
        score = abs(math.log(width / ((n - 1) * lane)))
        if best is None or score < best[0]:
            best = (score, width, n)
    if best is None:
        raise ValueError(f"a {route_length:g} m route is too short for a survey at {altitude:g} m")
    _, width, n = best
    route = lawnmower(width, (n - 1) * lane, lane)
    centre = np.array([width / 2, (n - 1) * lane / 2])
    return Route(route.points - centre, closed=False)


def terrain_world(rng: np.random.Generator, route_length: float,
                  altitude: float, pitch_deg: float = PITCH_DEG) -> tuple[Scene, Route]:
    """Build the terrain scene and the survey route over it."""
    route = survey_route(route_length, altitude, pitch_deg)
    lo, hi = route.points.min(axis=0), route.points.max(axis=0)
    # What the camera can see beyond the route: half a footprint diagonal (nadir), or
    # much further for a camera looking ahead.
    margin = 0.9 * footprint_width(altitude) + 10.0 if pitch_deg <= -45 else 60.0
    extent = np.array([lo[0] - margin, lo[1] - margin, hi[0] + margin, hi[1] + margin])
    texel = float(np.clip(altitude / 600.0, 0.03, 0.15))
    scene = Scene(extent=extent)
    land = parcels(rng, extent)
    roads = _roads(rng, extent)
    obj_texel = 2 * texel
    _yards(scene, rng, land, extent, obj_texel)
    _trees(scene, rng, land, extent, roads, obj_texel)
    ground = terrain_ground(rng, land, extent, texel, roads)
    scene.planes.insert(0, ground_plane(ground, extent, texel))
    return scene, route


def _roads(rng, extent) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """One or two roads right across the area and a few farm tracks."""
    xmin, ymin, xmax, ymax = extent
    size = max(xmax - xmin, ymax - ymin)
    centre = np.array([(xmin + xmax) / 2, (ymin + ymax) / 2])
    out = []
    for k in range(int(rng.integers(1, 3)) + int(rng.integers(2, 5))):
        a = rng.uniform(0, math.pi)
        d = np.array([math.cos(a), math.sin(a)])
        offset = rng.uniform(-0.35, 0.35) * size * np.array([-d[1], d[0]])
        width = rng.uniform(5.0, 7.0) if k == 0 or (k == 1 and rng.random() < 0.5) else rng.uniform(2.0, 3.0)
        out.append((centre + offset - d * size, centre + offset + d * size, width))
    return out


def _yards(scene: Scene, rng, land, extent, texel) -> None:
    """Farm buildings and parked cars in the yard parcels."""
    for seed, use in zip(land.seeds, land.uses, strict=True):
        if use != "yard" or not _inside(extent, seed, 8.0):
            continue
        yaw = rng.uniform(0, math.pi)
        along, across = np.array([math.cos(yaw), math.sin(yaw)]), np.array([-math.sin(yaw), math.cos(yaw)])
        for k in range(int(rng.integers(1, 4))):
            centre = seed + along * rng.uniform(-10, 10) + across * (k * 13.0 - 10.0)
            add_building(scene, rng, centre, rng.uniform(8, 20), rng.uniform(6, 12),
                         rng.uniform(4.0, 10.0), yaw, texel)
        for _ in range(int(rng.integers(0, 4))):
            p = seed + along * rng.uniform(-12, 12) + across * rng.uniform(4, 8)
            owner = add_car(scene, rng, p, yaw + rng.uniform(-0.3, 0.3), texel, max_distance=np.inf)
            if rng.random() < 0.5:
                scene.transient.add(owner)


def _trees(scene: Scene, rng, land, extent, roads, texel) -> None:
    """Rows of trees along the roads, orchards in a grid, woods as clusters."""
    count = 0
    limit = 260
    for start, end, width in roads:
        d = end - start
        length = float(np.linalg.norm(d))
        n = np.array([-d[1], d[0]]) / length
        t = rng.uniform(0, 12)
        while t < length and count < limit:
            p = start + d * (t / length) + n * (width / 2 + 2.5)
            if _inside(extent, p, 2.0) and rng.random() < 0.5:
                add_tree(scene, rng, p, texel, max_distance=np.inf)
                count += 1
            t += rng.uniform(8, 16)
    for seed, use in zip(land.seeds, land.uses, strict=True):
        if use == "orchard":
            a = rng.uniform(0, math.pi)
            u, v = np.array([math.cos(a), math.sin(a)]), np.array([-math.sin(a), math.cos(a)])
            for i in range(-2, 3):
                for j in range(-2, 3):
                    p = seed + 6.0 * (i * u + j * v)
                    if count < limit and _inside(extent, p, 2.0) and land.use_at(extent, *p) == "orchard":
                        add_tree(scene, rng, p, texel, height=float(rng.uniform(3.5, 5.5)),
                                 max_distance=np.inf)
                        count += 1
        elif use == "forest":
            for _ in range(int(rng.integers(10, 25))):
                p = seed + rng.normal(0, 8.0, 2)
                if count < limit and _inside(extent, p, 2.0) and land.use_at(extent, *p) == "forest":
                    add_tree(scene, rng, p, texel, height=float(rng.uniform(8.0, 16.0)),
                             max_distance=np.inf)
                    count += 1


def _inside(extent, p, pad) -> bool:
    return bool(extent[0] + pad < p[0] < extent[2] - pad and extent[1] + pad < p[1] < extent[3] - pad)


def uav_poses(route: Route, rng: np.random.Generator, *, frames: int, spacing: float,
              altitude: float, pitch_deg: float) -> list[Pose]:
    """Camera poses of one flight along the route.

    Gusts make the spacing uneven (30 %) and push the UAV up to a few metres off the
    route; the altitude differs between passes by up to 10 % and wanders by half a metre;
    the camera's yaw is the flight direction plus an offset that differs between passes
    (up to 45 degrees) plus a few degrees of wobble; pitch and roll wobble by 3 degrees.
    """
    traj = follow(route, rng, frames=frames, spacing=spacing, lateral_m=3.0,
                  lateral_wavelength=40.0, speed_jitter=0.3, yaw_jitter_deg=5.0)
    yaw_offset = math.radians(rng.uniform(-45.0, 45.0)) if pitch_deg <= -45 else 0.0
    z = altitude * rng.uniform(0.9, 1.1) + smooth_noise(rng, traj.s, 30.0, 0.5)
    pitch = math.radians(pitch_deg) + np.radians(smooth_noise(rng, traj.s, 20.0, 3.0))
    roll = np.radians(smooth_noise(rng, traj.s, 20.0, 3.0))
    return [Pose(np.array([x, y, h]), float(yaw + yaw_offset), float(p), float(r))
            for (x, y), yaw, h, p, r in zip(traj.xy, traj.yaw, z, pitch, roll, strict=True)]
