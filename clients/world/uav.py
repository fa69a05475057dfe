"""The UAV world of Flyphone (Erhard et al., section 5.1).

A quadcopter flies a survey over open land: fields, meadows, farm yards with buildings,
orchards, woods, ponds, roads and tracks. The camera looks straight down by default
(``pitch_deg=-90``) from 5 to 100 m; a forward-looking camera (pitch above -45 degrees)
flies a loop instead, as Flyphone's phone did round its courtyard at 5 to 10 m. Frames
are further apart than the robot's and unevenly so ("the distances between images vary
because of gusts of wind"), each pass flies a few metres off the others at a slightly
different altitude, and the camera's yaw differs between passes.

With ``relief_m`` the land is not flat: the ground rises and falls in hills (a smooth
random profile across the survey, built of strips each tilted about the north axis, as the
renderer draws planes), and every building, car and tree stands on the ground beneath it.
"""

from __future__ import annotations

import math
from dataclasses import replace

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


HILL_WAVELENGTH = 160.0
"""Metres between hilltops of a world with relief."""

STRIP = 12.0
"""Width (m) of the tilted strips a world with relief draws its ground with."""


def terrain_world(rng: np.random.Generator, route_length: float,
                  altitude: float, pitch_deg: float = PITCH_DEG,
                  relief_m: float = 0.0) -> tuple[Scene, Route]:
    """Build the terrain scene and the survey route over it; ``relief_m`` is the height
    from valley to hilltop (0: flat land)."""
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
    if relief_m > 0:
        add_relief(scene, hill_profile(rng, extent, relief_m))
    return scene, route


def hill_profile(rng: np.random.Generator, extent: np.ndarray,
                 relief_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Ground heights (x, z) every :data:`STRIP` metres across ``extent``: two sinusoids
    with random phases, scaled so that valley to hilltop is ``relief_m``."""
    x = np.arange(extent[0], extent[2] + STRIP, STRIP)
    phase = rng.uniform(0.0, 2 * math.pi, 2)
    z = (np.sin(2 * math.pi * x / HILL_WAVELENGTH + phase[0])
         + 0.4 * np.sin(2 * math.pi * x / (0.45 * HILL_WAVELENGTH) + phase[1]))
    z = (z - z.min()) / max(np.ptp(z), 1e-9) * relief_m
    return x, z


def ground_height(profile: tuple[np.ndarray, np.ndarray], x) -> np.ndarray:
    """Height of the ground at east ``x`` (flat beyond the profile's ends)."""
    return np.interp(x, *profile)


def add_relief(scene: Scene, profile: tuple[np.ndarray, np.ndarray]) -> None:
    """Replace the flat ground (the scene's first quad) by strips that follow ``profile``,
    and stand every object on the ground beneath its centre."""
    flat = scene.planes[0]
    xs, zs = profile
    texel = float(flat.u[0])
    c0, r0, c1, r1 = flat.span
    x0 = float(flat.origin[0])  # east of texel column 0

    def column(x: float) -> float:
        return (x - x0) / texel

    strips = []
    edges = [(c0, column(xs[0]), 0.0, zs[0], xs[0])]
    edges += [(column(a), column(b), (zb - za) / (b - a), za, a)
              for a, b, za, zb in zip(xs[:-1], xs[1:], zs[:-1], zs[1:], strict=True)]
    edges.append((column(xs[-1]), c1, 0.0, zs[-1], xs[-1]))
    width = flat.size[0]
    for ca, cb, slope, z_start, x_start in edges:
        # each strip its own columns of the texture: the pass shades every quad's texture
        i0 = int(np.clip(math.floor(ca + 0.5), 0, width - 1))
        i1 = int(np.clip(math.ceil(cb + 0.5), i0 + 1, width))
        origin = flat.origin + np.array([i0 * texel, 0.0, 0.0])
        origin[2] = z_start + slope * (origin[0] - x_start)
        strips.append(replace(flat, origin=origin, u=np.array([texel, 0.0, texel * slope]),
                              albedo=np.ascontiguousarray(flat.albedo[:, i0:i1]),
                              span=(ca - i0, r0, cb - i0, r1)))
    heights = {}
    for plane in scene.planes[1:]:
        heights.setdefault(plane.owner, []).append(plane.corners()[:, :2])
    for solid in scene.solids:
        heights.setdefault(solid.owner, []).append(solid.points[:, :2])
    lift = {owner: float(ground_height(profile, np.concatenate(pts)[:, 0].mean()))
            for owner, pts in heights.items()}
    for plane in scene.planes[1:]:
        plane.origin = plane.origin + np.array([0.0, 0.0, lift[plane.owner]])
    for solid in scene.solids:
        solid.faces = [f + np.array([0.0, 0.0, lift[solid.owner]]) for f in solid.faces]
    scene.planes[0:1] = strips


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
              altitude: float, pitch_deg: float, relief_m: float = 0.0) -> list[Pose]:
    """Camera poses of one flight along the route.

    Over hills (``relief_m``) the UAV holds its altitude above its take-off point, as a
    survey flown on barometric altitude does: ``altitude`` over the hilltops, up to
    ``altitude + relief_m`` over the valleys.

    Gusts make the spacing uneven (30 %) and push the UAV up to a few metres off the
    route; the altitude differs between passes by up to 10 % and wanders by half a metre;
    the camera's yaw is the flight direction plus an offset that differs between passes
    (up to 45 degrees) plus a few degrees of wobble; pitch and roll wobble by 3 degrees.
    """
    traj = follow(route, rng, frames=frames, spacing=spacing, lateral_m=3.0,
                  lateral_wavelength=40.0, speed_jitter=0.3, yaw_jitter_deg=5.0)
    yaw_offset = math.radians(rng.uniform(-45.0, 45.0)) if pitch_deg <= -45 else 0.0
    z = altitude * rng.uniform(0.9, 1.1) + smooth_noise(rng, traj.s, 30.0, 0.5) + relief_m
    pitch = math.radians(pitch_deg) + np.radians(smooth_noise(rng, traj.s, 20.0, 3.0))
    roll = np.radians(smooth_noise(rng, traj.s, 20.0, 3.0))
    return [Pose(np.array([x, y, h]), float(yaw + yaw_offset), float(p), float(r))
            for (x, y), yaw, h, p, r in zip(traj.xy, traj.yaw, z, pitch, roll, strict=True)]
