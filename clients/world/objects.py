"""Scene objects built from textured quads: buildings, cars, trees, bushes, street lamps.

Each builder appends the object's quads and its shadow-casting solid to a
:class:`~clients.world.scene.Scene` and returns the object's owner id. Sizes follow
ordinary streets: cars 3.8-4.8 m long, street trees 5-11 m high, buildings of two to six
floors.
"""

from __future__ import annotations

import math

import numpy as np

from vloc.clients.world.facades import facade, facade_style, roof
from vloc.clients.world.scene import (
    UP,
    Scene,
    Solid,
    box_corners,
    box_side_frames,
    box_solid,
    plane_from_rect,
)
from vloc.clients.world.textures import (
    CAR_COLOURS,
    bark,
    car_body_side,
    car_end,
    foliage,
    glass_band,
    jitter_colour,
    tinted,
)

DOWN = -UP


def add_building(scene: Scene, rng: np.random.Generator, centre: np.ndarray, length: float,
                 depth: float, height: float, yaw: float, texel: float,
                 face_wanted=None) -> int:
    """A box building with textured facades and a roof.

    Parameters
    ----------
    centre : (2,) float
        Centre of the footprint (east, north).
    length, depth : float
        Footprint along ``yaw`` and across it, metres.
    face_wanted : callable or None
        ``face_wanted(centre, normal) -> bool``; facades nobody can see are skipped (their
        solid still casts shadows).
    """
    owner = scene.new_owner()
    style = facade_style(rng)
    corners = box_corners(np.array([centre[0], centre[1], 0.0]),
                          np.array([length / 2, depth / 2, height]), yaw)
    for top_left, right, width, h in box_side_frames(corners):
        normal = np.cross(DOWN, right)
        mid = top_left + right * width / 2
        if face_wanted is not None and not face_wanted(mid[:2], normal):
            continue
        tex = facade(rng, style, width, h, texel)
        scene.planes.append(plane_from_rect(top_left, right, DOWN, width, h, tex, owner=owner,
                                            receives_shadows=True))
    along = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    across = np.array([-math.sin(yaw), math.cos(yaw), 0.0])
    scene.planes.append(plane_from_rect(corners[7], along, -across, length, depth,
                                        roof(rng, length, depth, texel * 2), owner=owner,
                                        receives_shadows=True))
    scene.solids.append(box_solid(corners, owner))
    return owner


def add_car(scene: Scene, rng: np.random.Generator, centre: np.ndarray, yaw: float,
            texel: float, max_distance: float = 70.0) -> int:
    """A parked car: a body box with wheels and a glazed cabin on top."""
    owner = scene.new_owner()
    length, width = rng.uniform(3.8, 4.8), rng.uniform(1.65, 1.9)
    body_h, total_h = rng.uniform(0.85, 1.0), rng.uniform(1.35, 1.6)
    colour = jitter_colour(rng, CAR_COLOURS[int(rng.integers(len(CAR_COLOURS)))], 8)
    clearance = 0.17
    base = np.array([centre[0], centre[1], 0.0])
    body = box_corners(base, np.array([length / 2, width / 2, body_h]), yaw)
    along = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    across = np.array([-math.sin(yaw), math.cos(yaw), 0.0])
    kw = dict(owner=owner, max_distance=max_distance)
    rows = max(4, int(round(body_h / texel)))
    for k, (top_left, right, w, h) in enumerate(box_side_frames(body)):
        cols = max(4, int(round(w / texel)))
        if k % 2 == 0:          # the long sides
            tex, alpha = car_body_side(rng, colour, cols, rows, texel, (0.2, 0.8), clearance)
        else:                   # front (+along) and back
            tex, alpha = car_end(rng, colour, cols, rows, k == 1,
                                 max(1, int(round(clearance / texel))))
        scene.planes.append(plane_from_rect(top_left, right, DOWN, w, h, tex, alpha=alpha, **kw))
    bonnet = tinted(rng, (max(4, int(width / texel)), max(4, int(length / texel))), colour, 10, 0.04, 2)
    scene.planes.append(plane_from_rect(body[7], along, -across, length, width, bonnet, **kw))
    _add_cabin(scene, rng, base + UP * body_h, along, across, length, width,
               total_h - body_h, colour, texel, kw)
    scene.solids.append(box_solid(body, owner))
    return owner


def _add_cabin(scene: Scene, rng, base: np.ndarray, along, across, length: float, width: float,
               height: float, colour, texel: float, kw: dict) -> None:
    """The glazed cabin on a car body: sloping windscreen and rear window, side windows
    cut to the trapezoid by their coverage, a flat roof."""
    cab_len = length * rng.uniform(0.5, 0.62)
    front, back = rng.uniform(0.45, 0.8) * height / 0.5, rng.uniform(0.15, 0.45) * height / 0.5
    centre = base + along * (-length * 0.06)
    half_w = width / 2 - 0.08
    lo, hi = centre - along * cab_len / 2, centre + along * cab_len / 2   # base back, front
    top_back, top_front = lo + along * back + UP * height, hi - along * front + UP * height
    rows = max(4, int(round(height / texel)))
    for sign in (-1.0, 1.0):                       # side windows (-across, then +across)
        right = along if sign < 0 else -along
        start = (lo if sign < 0 else hi) + sign * across * half_w + UP * height
        cols = max(4, int(round(cab_len / texel)))
        tex = glass_band(rng, colour, cols, rows, 2)
        # Along-coordinate of every column and height of every row -> inside the trapezoid?
        a = (np.arange(cols) + 0.5) / cols * cab_len
        a = a if sign < 0 else cab_len - a                  # distance from the back end
        z = 1.0 - (np.arange(rows) + 0.5) / rows            # height share, top row = 1
        inside = (a[None, :] >= back * z[:, None]) & (a[None, :] <= cab_len - front * z[:, None])
        alpha = np.where(inside, 255, 0).astype(np.uint8)
        scene.planes.append(plane_from_rect(start, right, DOWN, cab_len, height, tex,
                                            alpha=alpha, **kw))
    for top, bottom, right in ((top_front, hi, across), (top_back, lo, -across)):
        slope = bottom - top
        slant = float(np.linalg.norm(slope))
        tex = glass_band(rng, colour, max(4, int(2 * half_w / texel)), max(4, int(slant / texel)), 1)
        scene.planes.append(plane_from_rect(top - right * half_w, right, slope / slant,
                                            2 * half_w, slant, tex, **kw))
    roof_len = float(np.dot(top_front - top_back, along))
    top = tinted(rng, (max(4, int(2 * half_w / texel)), max(4, int(roof_len / texel))), colour, 10, 0.04, 2)
    scene.planes.append(plane_from_rect(top_back + across * half_w, along, -across, roof_len,
                                        2 * half_w, top, **kw))
    corners = np.array([lo - across * half_w, hi - across * half_w, hi + across * half_w,
                        lo + across * half_w, top_back - across * half_w,
                        top_front - across * half_w, top_front + across * half_w,
                        top_back + across * half_w])
    scene.solids.append(box_solid(corners, kw["owner"]))


TREE_GREENS = ((40, 110, 60), (35, 90, 45), (50, 120, 90), (30, 80, 70), (45, 130, 110))


def add_tree(scene: Scene, rng: np.random.Generator, position: np.ndarray, texel: float,
             height: float | None = None, max_distance: float = 120.0) -> int:
    """A tree: a trunk of two crossed quads and a crown of six half billboards around it,
    plus a disc on top for views from above."""
    owner = scene.new_owner()
    height = float(rng.uniform(5.0, 11.0)) if height is None else height
    crown_r = float(rng.uniform(0.22, 0.35) * height)
    crown_h = float(rng.uniform(0.45, 0.65) * height)
    trunk_top = height - crown_h
    centre = np.array([position[0], position[1], trunk_top + crown_h / 2])
    green = TREE_GREENS[int(rng.integers(len(TREE_GREENS)))]
    kw = dict(owner=owner, max_distance=max_distance, two_sided=True)
    phase = rng.uniform(0, math.pi)
    trunk_w = 0.12 * crown_r + 0.1
    for k in range(2):
        a = phase + k * math.pi / 2
        d = np.array([math.cos(a), math.sin(a), 0.0])
        top_left = np.array([position[0], position[1], trunk_top + crown_h * 0.4]) - d * trunk_w / 2
        tex = bark(rng, max(2, int(trunk_w / texel)), max(4, int((trunk_top + crown_h * 0.4) / texel)))
        scene.planes.append(plane_from_rect(top_left, d, DOWN, trunk_w, trunk_top + crown_h * 0.4, tex, **kw))
    size = (max(4, int(crown_r / texel)), max(4, int(crown_h / texel)))
    for k in range(6):
        a = phase + k * math.pi / 3 + rng.uniform(-0.15, 0.15)
        d = np.array([math.cos(a), math.sin(a), 0.0])
        albedo, alpha = foliage(rng, size[0], size[1], green)
        top_left = np.array([position[0], position[1], height])
        scene.planes.append(plane_from_rect(top_left, d, DOWN, crown_r, crown_h, albedo,
                                            alpha=alpha, foliage=True, **kw))
    disc_px = max(4, int(2 * crown_r / texel))
    albedo, alpha = foliage(rng, disc_px, disc_px, green, half=False)
    top_left = np.array([position[0] - crown_r, position[1] + crown_r, centre[2] + crown_h * 0.15])
    scene.planes.append(plane_from_rect(top_left, np.array([1.0, 0, 0]), np.array([0, -1.0, 0]),
                                        2 * crown_r, 2 * crown_r, albedo, alpha=alpha,
                                        foliage=True, owner=owner, max_distance=max_distance))
    scene.solids.append(Solid(ellipsoid_faces(centre, crown_r, crown_h / 2, rng), owner,
                              soft=0.2, porosity=0.3))
    scene.solids.append(box_solid(box_corners(np.array([position[0], position[1], 0.0]),
                                              np.array([trunk_w / 2, trunk_w / 2, trunk_top]), 0.0),
                                  owner))
    return owner


def add_bush(scene: Scene, rng: np.random.Generator, position: np.ndarray, texel: float,
             max_distance: float = 60.0) -> int:
    """A bush: two crossed billboards resting on the ground."""
    owner = scene.new_owner()
    h, w = float(rng.uniform(0.5, 1.6)), float(rng.uniform(0.9, 2.8))
    green = jitter_colour(rng, TREE_GREENS[int(rng.integers(len(TREE_GREENS)))], 12)
    phase = rng.uniform(0, math.pi)
    for k in range(2):
        a = phase + k * math.pi / 2
        d = np.array([math.cos(a), math.sin(a), 0.0])
        albedo, alpha = foliage(rng, max(4, int(w / texel)), max(4, int(h / texel)), green, half=False)
        # The lower half of the billboard touches the ground: no gap under a bush.
        alpha[alpha.shape[0] * 2 // 3:] = np.maximum(alpha[alpha.shape[0] * 2 // 3:], 255 * (
            np.abs(np.linspace(-1, 1, alpha.shape[1])) < 0.8)[None, :].astype(np.uint8))
        top_left = np.array([position[0], position[1], h]) - d * w / 2
        scene.planes.append(plane_from_rect(top_left, d, DOWN, w, h, albedo, alpha=alpha,
                                            two_sided=True, foliage=True, owner=owner,
                                            max_distance=max_distance))
    scene.solids.append(Solid(ellipsoid_faces(np.array([position[0], position[1], h / 2]),
                                              w / 2, h / 2, rng), owner, soft=0.1, porosity=0.15))
    return owner


def add_lamp(scene: Scene, rng: np.random.Generator, position: np.ndarray, texel: float,
             max_distance: float = 80.0) -> int:
    """A street lamp: a thin pole of two crossed quads and a lamp head box."""
    owner = scene.new_owner()
    height = float(rng.uniform(4.0, 6.0))
    pole_w = 0.14
    colour = jitter_colour(rng, (70, 75, 70), 15)
    for k in range(2):
        d = np.array([math.cos(k * math.pi / 2), math.sin(k * math.pi / 2), 0.0])
        tex = tinted(rng, (max(4, int(height / texel)), max(2, int(pole_w / texel))), colour, 6, 0.1, 2)
        scene.planes.append(plane_from_rect(np.array([position[0], position[1], height]) - d * pole_w / 2,
                                            d, DOWN, pole_w, height, tex, two_sided=True,
                                            owner=owner, max_distance=max_distance))
    head = box_corners(np.array([position[0], position[1], height]), np.array([0.3, 0.18, 0.25]),
                       float(rng.uniform(0, math.pi)))
    for top_left, right, w, h in box_side_frames(head):
        tex = tinted(rng, (max(4, int(h / texel)), max(4, int(w / texel))), (200, 220, 230), 4, 0.1, 2)
        scene.planes.append(plane_from_rect(top_left, right, DOWN, w, h, tex, owner=owner,
                                            max_distance=max_distance))
    scene.solids.append(box_solid(box_corners(np.array([position[0], position[1], 0.0]),
                                              np.array([pole_w / 2, pole_w / 2, height]), 0.0), owner))
    return owner


def ellipsoid_faces(centre: np.ndarray, r: float, rz: float, rng: np.random.Generator,
                    n_lat: int = 4, n_lon: int = 8) -> list[np.ndarray]:
    """Quad faces of a slightly ragged ellipsoid: the shadow caster of a crown."""
    lat = np.linspace(-math.pi / 2, math.pi / 2, n_lat + 1)
    lon = np.linspace(0, 2 * math.pi, n_lon, endpoint=False)
    ragged = 1.0 + 0.12 * rng.uniform(-1, 1, (n_lat + 1, n_lon))
    pts = np.stack([r * np.cos(lat)[:, None] * np.cos(lon)[None, :] * ragged,
                    r * np.cos(lat)[:, None] * np.sin(lon)[None, :] * ragged,
                    rz * np.sin(lat)[:, None] * np.ones_like(lon)[None, :]], axis=-1) + centre
    faces = []
    for i in range(n_lat):
        for j in range(n_lon):
            jj = (j + 1) % n_lon
            faces.append(np.array([pts[i, j], pts[i, jj], pts[i + 1, jj], pts[i + 1, j]]))
    return faces
