"""Scenes made of textured planar quads, and the solids that cast their shadows.

A scene is a list of :class:`Plane` quads (ground, facades, roofs, car body faces, the
crossed billboards of trees and bushes), each carrying an albedo texture, plus a list of
:class:`Solid` occluders (convex polyhedra as lists of faces) used only to cast sun shadows.
The renderer draws every quad with one homography (texture plane -> image) and a depth
buffer, so perspective and parallax are exact for every plane.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

UP = np.array([0.0, 0.0, 1.0])


@dataclass(eq=False)
class Plane:
    """A textured planar quad.

    The texel at column ``c`` and row ``r`` (pixel centres at integers) lies at the world
    point ``origin + c * u + r * v``; the quad spans the whole texture.

    Attributes
    ----------
    origin : (3,) float64 ndarray
        World position of the centre of texel (0, 0).
    u, v : (3,) float64 ndarray
        World step of one texel along texture columns and rows.
    albedo : (h, w, 3) uint8 ndarray
        Reflectance texture, BGR.
    alpha : (h, w) uint8 ndarray or None
        Coverage for cut-out quads (foliage); texels below 128 are holes.
    two_sided : bool
        Seen from both sides (billboards); otherwise back faces are culled.
    foliage : bool
        Lit as a tree crown or bush (translucent leaves) rather than as a flat surface.
    owner : int
        Id of the object the quad belongs to; an object casts no shadow on itself.
    max_distance : float
        Not drawn when the camera is farther than this from the quad (small objects).
    receives_shadows : bool
        Whether cast shadows are baked into the texture per illumination.
    span : (4,) tuple of float or None
        Texel rectangle (c0, r0, c1, r1) the quad covers when it is not the texture
        itself: the ground reaches beyond its texture, which repeats mirrored there.
    """

    origin: np.ndarray
    u: np.ndarray
    v: np.ndarray
    albedo: np.ndarray
    alpha: np.ndarray | None = None
    two_sided: bool = False
    foliage: bool = False
    owner: int = -1
    max_distance: float = np.inf
    receives_shadows: bool = False
    span: tuple[float, float, float, float] | None = None

    @property
    def size(self) -> tuple[int, int]:
        """Texture (width, height) in texels."""
        return self.albedo.shape[1], self.albedo.shape[0]

    @cached_property
    def normal(self) -> np.ndarray:
        """(3,) unit front normal: the side from which the texture reads unmirrored."""
        n = np.cross(self.v, self.u)
        return n / np.linalg.norm(n)

    def corners(self) -> np.ndarray:
        """(4, 3) float64 world corners of the quad (outer texel edges), in order."""
        w, h = self.size
        c0, r0, c1, r1 = self.span if self.span is not None else (-0.5, -0.5, w - 0.5, h - 0.5)
        tex = np.array([[c0, r0], [c1, r0], [c1, r1], [c0, r1]])
        return self.origin + tex[:, :1] * self.u + tex[:, 1:] * self.v

    def texel_of(self, points: np.ndarray) -> np.ndarray:
        """(N, 2) texture coordinates (column, row) of world points lying on the plane."""
        basis = np.stack([self.u, self.v], axis=1)  # (3, 2)
        coords, *_ = np.linalg.lstsq(basis, (np.asarray(points) - self.origin).T, rcond=None)
        return coords.T


def plane_from_rect(top_left: np.ndarray, right: np.ndarray, down: np.ndarray,
                    width_m: float, height_m: float, albedo: np.ndarray,
                    **kwargs) -> Plane:
    """A quad from its top-left corner, unit right/down directions and size in metres.

    The texture is stretched over the rectangle; its texel size follows from the texture's
    shape, so callers choose the resolution when they make the texture.
    """
    h, w = albedo.shape[:2]
    u = np.asarray(right, np.float64) * (width_m / w)
    v = np.asarray(down, np.float64) * (height_m / h)
    origin = np.asarray(top_left, np.float64) + 0.5 * u + 0.5 * v
    return Plane(origin=origin, u=u, v=v, albedo=albedo, **kwargs)


@dataclass(eq=False)
class Solid:
    """A convex occluder for shadow casting.

    Attributes
    ----------
    faces : list of (k, 3) float64 ndarray
        Convex polygons whose union bounds the solid (or a single silhouette disc).
    owner : int
        Id shared with the object's planes.
    soft : float
        Penumbra width in metres (blur of the cast shadow's edge).
    porosity : float
        Share of light that passes (leaf gaps), 0 for solid objects.
    """

    faces: list[np.ndarray]
    owner: int
    soft: float = 0.05
    porosity: float = 0.0

    @property
    def points(self) -> np.ndarray:
        return np.concatenate(self.faces, axis=0)


@dataclass(eq=False)
class Scene:
    """Everything the renderer and the shading need for one world.

    Attributes
    ----------
    planes : list of Plane
    solids : list of Solid
    extent : (4,) float64 ndarray
        xmin, ymin, xmax, ymax of the textured ground in metres.
    transient : set of int
        Owners that come and go between passes (parked cars); each pass draws which of
        them are there.
    """

    planes: list[Plane] = field(default_factory=list)
    solids: list[Solid] = field(default_factory=list)
    extent: np.ndarray = field(default_factory=lambda: np.zeros(4))
    transient: set[int] = field(default_factory=set)
    _next_owner: int = 0

    def new_owner(self) -> int:
        self._next_owner += 1
        return self._next_owner

    def without(self, absent: set[int]) -> tuple[list[Plane], list[Solid]]:
        """The quads and solids of the objects that are not ``absent``."""
        return ([p for p in self.planes if p.owner not in absent],
                [s for s in self.solids if s.owner not in absent])


def ground_plane(albedo: np.ndarray, extent: np.ndarray, texel: float,
                 reach: float = 3000.0) -> Plane:
    """The ground z = 0 textured over ``extent`` (xmin, ymin, xmax, ymax) and reaching
    ``reach`` metres beyond it (mirrored texture there, seen only near the horizon).

    Texture columns run east, rows south.
    """
    xmin, _, _, ymax = (float(v) for v in extent)
    h, w = albedo.shape[:2]
    far = reach / texel
    return Plane(origin=np.array([xmin + texel / 2, ymax - texel / 2, 0.0]),
                 u=np.array([texel, 0.0, 0.0]), v=np.array([0.0, -texel, 0.0]),
                 albedo=albedo, owner=0, receives_shadows=True,
                 span=(-0.5 - far, -0.5 - far, w - 0.5 + far, h - 0.5 + far))


def box_corners(centre: np.ndarray, half: np.ndarray, yaw: float) -> np.ndarray:
    """(8, 3) corners of a box resting on ``centre[2]``: bottom four then top four.

    ``half`` is (half length along yaw, half width across, full height).
    """
    c, s = np.cos(yaw), np.sin(yaw)
    along, across = np.array([c, s, 0.0]), np.array([-s, c, 0.0])
    base = [centre + sa * half[0] * along + sb * half[1] * across
            for sa, sb in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
    bottom = np.array(base)
    return np.concatenate([bottom, bottom + half[2] * UP])


def box_solid(corners: np.ndarray, owner: int, soft: float = 0.05) -> Solid:
    """The six faces of a box from :func:`box_corners`."""
    b, t = corners[:4], corners[4:]
    faces = [b, t] + [np.array([b[i], b[(i + 1) % 4], t[(i + 1) % 4], t[i]]) for i in range(4)]
    return Solid(faces=faces, owner=owner, soft=soft)


def box_side_frames(corners: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, float, float]]:
    """Outward-facing side faces of a box as (top_left, right, width_m, height_m).

    Faces are ordered along the box's own axes: -across (the right-hand side when
    looking along yaw), +along (front), +across, -along (back). ``right`` is the unit
    direction of the texture's columns as seen from outside; rows run down.
    """
    b, t = corners[:4], corners[4:]
    frames = []
    for i in range(4):
        p0, p1 = b[i], b[(i + 1) % 4]
        width = float(np.linalg.norm(p1 - p0))
        height = float(t[i][2] - b[i][2])
        right = (p1 - p0) / width
        frames.append((t[i].copy(), right, width, height))
    return frames

