"""One traversal of a world: which objects are there, how they are lit, and its frames.

Per pass, the parked cars that come and go are drawn, every quad's texture is shaded under
the pass's illumination with its cast shadows baked in (texture space, once per pass),
and a :class:`~clients.world.render.Renderer` draws the frames.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np

from vloc.clients.world.camera import Camera, Pose
from vloc.clients.world.lighting import (
    AutoExposure,
    Illumination,
    camera_response,
    shade,
    shadow_mask,
    sky_panorama,
)
from vloc.clients.world.render import Renderer
from vloc.clients.world.scene import Plane, Scene, Solid

TRANSIENT_ABSENT = 0.35
"""Chance that a car that comes and goes is missing in a pass."""


def prepare_pass(scene: Scene, illum: Illumination, camera: Camera, rng: np.random.Generator,
                 *, supersample: int = 2) -> tuple[Renderer, list[int]]:
    """Shade the scene for one pass.

    Returns
    -------
    renderer : Renderer
    absent : list of int
        Owners of the transient objects missing in this pass.
    """
    transient = sorted(scene.transient)
    absent = [o for o, r in zip(transient, rng.random(len(transient)), strict=True)
              if r < TRANSIENT_ABSENT]
    planes, solids = scene.without(set(absent))
    reach = _shadow_reach(illum, solids)
    centres = np.array([s.points.mean(axis=0) for s in solids]).reshape(-1, 3)
    shaded = []
    for plane in planes:
        shadow = None
        if plane.receives_shadows and illum.has_sun:
            near = _solids_near(plane, solids, centres, reach)
            shadow = shadow_mask(plane, near, illum, rng) if near else None
        shaded.append(shade(plane, illum, shadow))
    sky = sky_panorama(illum, rng)
    return Renderer(camera, planes, shaded, sky, supersample=supersample), absent


def render_frames(renderer: Renderer, poses: list[Pose], illum: Illumination,
                  rng: np.random.Generator) -> Iterator[np.ndarray]:
    """Frames of a pass after auto exposure and the camera response: (H, W, 3) uint8 BGR
    each."""
    exposure = AutoExposure(illum)
    for pose in poses:
        radiance = renderer.render(pose)
        yield camera_response(radiance, illum, rng, exposure(radiance))


def _shadow_reach(illum: Illumination, solids: list[Solid]) -> float:
    """How far from its caster a shadow can fall: the tallest solid over the tangent of
    the sun's elevation, capped (at dusk shadows run off to the horizon)."""
    if not solids or not illum.has_sun:
        return 0.0
    top = max(float(s.points[:, 2].max()) for s in solids)
    return min(top / math.tan(math.radians(max(illum.sun_elevation_deg, 1.0))), 300.0)


def _solids_near(plane: Plane, solids: list[Solid], centres: np.ndarray,
                 reach: float) -> list[Solid]:
    corners = plane.corners()
    lo, hi = corners.min(axis=0)[:2] - reach - 10.0, corners.max(axis=0)[:2] + reach + 10.0
    keep = np.all((centres[:, :2] >= lo) & (centres[:, :2] <= hi), axis=1)
    return [s for s, k in zip(solids, keep, strict=True) if k and s.owner != plane.owner]
