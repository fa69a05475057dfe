"""The ground-robot world of Weiss et al. 2008 (section V, data set 1).

"Six rounds around a big building ... about 260 m long ... about 400 images ... streets,
buildings and cars, but also some bushes and trees": the route is a closed loop round a
block of buildings of different heights and styles, on a paved path between the buildings
and a street with parked cars, street trees and lamps; across the street stand more
buildings, and the roads continue past the corners as cross streets. A forward-looking
camera about 1 m above the ground takes one 320x240 image per second while the robot
drives at about 0.6 m/s.
"""

from __future__ import annotations

import math

import numpy as np

from vloc.clients.world.camera import Pose
from vloc.clients.world.objects import add_building, add_bush, add_car, add_lamp, add_tree
from vloc.clients.world.routes import Route, follow, rounded_rectangle, smooth_noise
from vloc.clients.world.scene import Scene, ground_plane
from vloc.clients.world.street import CURB, ROAD, SIDEWALK, Block, street_ground

SPACING = 0.6
"""Metres between frames: 0.6 m/s at one frame per second."""

ROUTE_LENGTH = 260.0
"""One round of data set 1 of Weiss et al."""

CAMERA_HEIGHT = 1.0
MIN_ROUTE = 24.0
FACADE_TEXEL = 0.03
GROUND_TEXEL = 0.03
OBJECT_TEXEL = 0.025

# Sides of the block: (along direction, outward normal, half length along, half across).
_SIDES = {"s": ((1.0, 0.0), (0.0, -1.0)), "e": ((0.0, 1.0), (1.0, 0.0)),
          "n": ((-1.0, 0.0), (0.0, 1.0)), "w": ((0.0, -1.0), (-1.0, 0.0))}


def block_for(route_length: float, rng: np.random.Generator) -> Block:
    """A block whose rounded-rectangle route has perimeter ``route_length``."""
    if route_length < MIN_ROUTE:
        raise ValueError(f"a robot route must be at least {MIN_ROUTE:g} m long, got {route_length:g}")
    aspect = float(rng.uniform(1.3, 1.9))
    radius = 0.0
    for _ in range(20):      # the radius depends on the size and the size on the radius
        hy = (route_length + (8 - 2 * math.pi) * radius) / (4 * (1 + aspect))
        radius = min(4.5, 0.35 * hy)
    return Block(half_x=aspect * hy, half_y=hy, radius=radius)


def street_world(rng: np.random.Generator, route_length: float) -> tuple[Scene, Route]:
    """Build the street scene and the route round its block.

    Parameters
    ----------
    rng : numpy.random.Generator
        Draws everything: block shape, buildings, textures, cars, trees.
    route_length : float
        Perimeter of the route, metres (260 m in Weiss et al.).
    """
    block = block_for(route_length, rng)
    route = rounded_rectangle(block.half_x, block.half_y, block.radius)
    scene = Scene()
    margin = CURB + ROAD + SIDEWALK + 18.0
    scene.extent = np.array([-block.half_x - margin, -block.half_y - margin,
                             block.half_x + margin, block.half_y + margin])
    boxes = _inner_buildings(rng, block) + _outer_buildings(rng, block)
    footprints = np.array([_footprint(b) for b in boxes])
    route_pts = route.points[:: max(1, len(route.points) // 80)]

    def face_wanted(mid, normal):
        return _seen_from_route(mid, normal, footprints, route_pts)

    for centre, length, depth, height, yaw in boxes:
        add_building(scene, rng, centre, length, depth, height, yaw, FACADE_TEXEL, face_wanted)
    _street_furniture(scene, rng, block, footprints)
    ground = street_ground(rng, block, scene.extent, GROUND_TEXEL)
    scene.planes.insert(0, ground_plane(ground, scene.extent, GROUND_TEXEL))
    return scene, route


def _row(rng, side: str, block: Block, distance: float, facing: float, span: tuple[float, float],
         depth: tuple[float, float], height: tuple[float, float], gap_p: float,
         setback: tuple[float, float]) -> list[tuple]:
    """Buildings along one side: facades on the line ``distance`` from the centre along the
    side's outward normal, facing ``facing`` (+1 outwards, -1 inwards)."""
    along, normal = (np.array(v) for v in _SIDES[side])
    a, out = span[0], []
    while a < span[1] - 2.0:
        if rng.random() < gap_p:
            a += rng.uniform(2.0, 7.0)
            continue
        length = min(rng.uniform(8.0, 22.0), span[1] - a)
        d, h, sb = rng.uniform(*depth), rng.uniform(*height), rng.uniform(*setback)
        q = distance - facing * sb - facing * d / 2
        centre = q * normal + (a + length / 2) * along
        out.append((centre, length, d, h, math.atan2(along[1], along[0])))
        a += length + (rng.uniform(0.0, 1.0) if rng.random() < 0.5 else 0.0)
    return out


def _inner_buildings(rng, block: Block) -> list[tuple]:
    hx, hy = block.half_x, block.half_y
    setback = (min(3.0, 0.3 * hy + 1.0), min(6.0, 0.45 * hy + 1.0))
    if hy < 9.0:      # a small block: one building fills it
        sb = rng.uniform(*setback)
        return [(np.zeros(2), 2 * (hx - sb), 2 * (hy - sb), rng.uniform(6.0, 14.0), 0.0)]
    out = []
    for side in "senw":
        half_along = hx if side in "sn" else hy
        half_across = hy if side in "sn" else hx
        inset = setback[1]
        out += _row(rng, side, block, half_across, 1.0, (-half_along + inset, half_along - inset),
                    (8.0, min(16.0, half_across)), (6.0, 19.0), 0.18, setback)
    return out


def _outer_buildings(rng, block: Block) -> list[tuple]:
    hx, hy = block.half_x, block.half_y
    street = CURB + ROAD + SIDEWALK
    out = []
    for side in "senw":
        half_along = hx if side in "sn" else hy
        half_across = hy if side in "sn" else hx
        out += _row(rng, side, block, half_across + street, -1.0,
                    (-half_along - CURB + 0.5, half_along + CURB - 0.5), (8.0, 14.0), (6.0, 22.0),
                    0.22, (0.0, 2.5))
    for sx in (-1, 1):          # corner blocks beyond the crossings
        for sy in (-1, 1):
            if rng.random() < 0.8:
                length, depth = rng.uniform(10, 20), rng.uniform(10, 20)
                cx = sx * (hx + street + rng.uniform(0, 2.0) + length / 2)
                cy = sy * (hy + street + rng.uniform(0, 2.0) + depth / 2)
                out.append((np.array([cx, cy]), length, depth, rng.uniform(7.0, 20.0), 0.0))
    return out


def _footprint(box) -> tuple[float, float, float, float]:
    """Axis-aligned footprint (xmin, ymin, xmax, ymax) of a building box."""
    centre, length, depth, _, yaw = box
    ex = abs(math.cos(yaw)) * length / 2 + abs(math.sin(yaw)) * depth / 2
    ey = abs(math.sin(yaw)) * length / 2 + abs(math.cos(yaw)) * depth / 2
    return (centre[0] - ex, centre[1] - ey, centre[0] + ex, centre[1] + ey)


def _seen_from_route(mid, normal, footprints: np.ndarray, route_pts: np.ndarray) -> bool:
    """Whether a facade can be seen from some route point: in front of it, within 150 m,
    and with no building footprint on the straight line between them (slab test)."""
    start = np.asarray(mid, np.float64) + 0.2 * np.asarray(normal[:2], np.float64)
    rel = route_pts - start
    front = (rel @ np.asarray(normal[:2]) > 0.3) & (np.hypot(rel[:, 0], rel[:, 1]) < 150.0)
    if not front.any():
        return False
    d = rel[front]                                          # (R, 2) segment directions
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t0 = (footprints[None, :, :2] - start) * inv[:, None, :]
        t1 = (footprints[None, :, 2:] - start) * inv[:, None, :]
    t_near = np.nanmax(np.minimum(t0, t1), axis=2)
    t_far = np.nanmin(np.maximum(t0, t1), axis=2)
    blocked = ((t_near < t_far) & (t_far > 0.0) & (t_near < 1.0)).any(axis=1)
    return bool((~blocked).any())


def _inside_any(p, footprints: np.ndarray, pad: float) -> bool:
    return bool(((footprints[:, 0] - pad < p[0]) & (p[0] < footprints[:, 2] + pad)
                 & (footprints[:, 1] - pad < p[1]) & (p[1] < footprints[:, 3] + pad)).any())


def _street_furniture(scene: Scene, rng, block: Block, footprints: np.ndarray) -> None:
    """Parked cars on both sides of each road, street trees, lamps and bushes."""
    hx, hy = block.half_x, block.half_y
    for side in "senw":
        along, normal = (np.array(v) for v in _SIDES[side])
        half_along = hx if side in "sn" else hy
        half_across = hy if side in "sn" else hx
        yaw = math.atan2(along[1], along[0])
        for lane in (CURB + 1.15, CURB + ROAD - 1.15):          # parking lanes
            a = -half_along + 5.0 + rng.uniform(0, 3)
            while a < half_along - 5.0:
                if rng.random() < 0.65:
                    p = (half_across + lane) * normal + a * along
                    owner = add_car(scene, rng, p, yaw + (math.pi if rng.random() < 0.5 else 0),
                                    OBJECT_TEXEL)
                    if rng.random() < 0.25:
                        scene.transient.add(owner)
                    a += rng.uniform(5.0, 6.5)
                else:
                    a += rng.uniform(2.0, 9.0)
        a = -half_along - CURB + rng.uniform(0, 6)                # trees across the street
        while a < half_along + CURB:
            p = (half_across + CURB + ROAD + 1.0) * normal + a * along
            if rng.random() < 0.8 and not _inside_any(p, footprints, 0.5):
                add_tree(scene, rng, p, OBJECT_TEXEL)
            a += rng.uniform(7.0, 13.0)
        a = -half_along + rng.uniform(3, 10)                      # lamps by the curb
        while a < half_along - 2.0:
            add_lamp(scene, rng, (half_across + CURB - 0.35) * normal + a * along, OBJECT_TEXEL)
            a += rng.uniform(18.0, 30.0)
        a = -half_along + 2.0                                      # bushes and small trees
        while a < half_along - 2.0:
            depth = rng.uniform(1.9, 5.0)
            p = (half_across - depth) * normal + a * along
            if not _inside_any(p, footprints, 0.3) and rng.random() < 0.55:
                if depth > 3.0 and rng.random() < 0.25:
                    add_tree(scene, rng, p, OBJECT_TEXEL, height=float(rng.uniform(3.5, 7.0)))
                else:
                    add_bush(scene, rng, p, OBJECT_TEXEL)
            a += rng.uniform(1.5, 5.0)


def robot_poses(route: Route, rng: np.random.Generator, *, frames: int,
                spacing: float) -> list[Pose]:
    """Camera poses of one round: about 0.6 m apart, a few tens of centimetres off the
    route to either side, the camera's yaw following the driving direction with a
    little wobble, and small pitch and roll from the uneven ground."""
    traj = follow(route, rng, frames=frames, spacing=spacing, lateral_m=0.35,
                  lateral_wavelength=15.0, speed_jitter=0.04, yaw_jitter_deg=1.5)
    pitch = np.radians(smooth_noise(rng, traj.s, 3.0, 1.0))
    roll = np.radians(smooth_noise(rng, traj.s, 3.0, 0.7))
    height = CAMERA_HEIGHT + smooth_noise(rng, traj.s, 2.0, 0.01)
    return [Pose(np.array([x, y, z]), float(yaw), float(p), float(r))
            for (x, y), yaw, p, r, z in zip(traj.xy, traj.yaw, pitch, roll, height, strict=True)]
