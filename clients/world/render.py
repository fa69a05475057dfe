"""Rendering a scene of textured quads with a pinhole camera.

Every quad is drawn with one homography from its texture plane to the image,
``H = K R [u | v | origin - C]`` (Hartley & Zisserman, eq. 8.1 restricted to a plane), so
perspective and parallax are exact. The quad is first clipped to the viewing frustum
(near plane and image borders) in the camera frame, which keeps the homography away from
points behind the camera; its projected polygon masks the warp. Visibility is resolved
with a per-pixel inverse-depth buffer: ``H^-1 (x, y, 1) = (c, r, 1) / z``, so the third
row of the inverse homography gives ``1 / z``, affine in the pixel, and the depth of a
whole quad costs three array operations. Textures are sampled from a mip-map pyramid at the level
whose texel footprint matches the pixel (the Jacobian determinant of the inverse
homography, ``det(H^-1) / w^3``), and frames are rendered at a multiple of the output
resolution and averaged down, which removes the aliasing that would otherwise create
keypoints that exist in one frame and not the next.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from vloc.clients.world.camera import Camera, Pose
from vloc.clients.world.lighting import SKY_BOTTOM_DEG
from vloc.clients.world.scene import Plane

NEAR = 0.05
"""Near clipping distance in metres."""

SKY_SUBSAMPLE = 4
"""The sky is smooth; it is looked up at 1/4 of the render resolution and interpolated."""


class Renderer:
    """Draws frames of one scene under one illumination.

    Parameters
    ----------
    camera : Camera
        Output camera.
    planes : list of Plane
        The quads present in this pass.
    shaded : list of (h, w, 3) uint8 ndarray
        Each quad's shaded texture (see :func:`clients.world.lighting.shade`).
    sky : (hs, ws, 3) uint8 ndarray
        Sky panorama: columns are compass bearings 0..360 degrees, rows elevations from
        90 degrees down to :data:`~clients.world.lighting.SKY_BOTTOM_DEG`.
    supersample : int
        Render at this multiple of the output resolution.
    """

    def __init__(self, camera: Camera, planes: list[Plane], shaded: list[np.ndarray],
                 sky: np.ndarray, *, supersample: int = 2) -> None:
        self.camera = camera
        self.supersample = supersample
        self.internal = camera.scaled(supersample)
        self.K = self.internal.matrix
        self.K_inv = np.linalg.inv(self.K)
        self.frustum = self.internal.frustum(NEAR)
        self.planes = planes
        self.pyramids = [_pyramid(tex, p.alpha) for tex, p in zip(shaded, planes, strict=True)]
        self.corners = np.array([p.corners() for p in planes]).reshape(-1, 4, 3)
        self.normals = np.array([p.normal for p in planes]).reshape(-1, 3)
        self.two_sided = np.array([p.two_sided for p in planes], bool)
        self.max_distance = np.array([p.max_distance for p in planes], np.float64)
        self.basis = np.array([np.stack([p.u, p.v, p.origin], axis=1) for p in planes]).reshape(-1, 3, 3)
        self.sky = np.ascontiguousarray(sky)
        w, h = self.internal.width, self.internal.height
        self._xs = np.arange(w, dtype=np.float32)
        self._ys = np.arange(h, dtype=np.float32)
        self._sky_rays = _pixel_rays(self.internal, SKY_SUBSAMPLE)

    def render(self, pose: Pose) -> np.ndarray:
        """Render one frame (before the camera response).

        Returns
        -------
        (H, W, 3) uint8 ndarray, BGR, at the camera's output resolution.
        """
        R, C = pose.rotation(), np.asarray(pose.position, np.float64)
        w, h = self.internal.width, self.internal.height
        image = self._sky_image(R, (w, h))
        inv_depth = np.zeros((h, w), np.float32)
        visible, cam, clip = self._visible(R, C)
        if len(visible):
            # Homographies texel -> pixel of all visible quads at once, and their inverses.
            KR = self.K @ R
            H = KR @ self.basis[visible]
            H[:, :, 2] -= KR @ C
            H_inv = np.linalg.inv(H)
            det = np.abs(np.linalg.det(H_inv))
            proj = cam @ self.K.T
            with np.errstate(divide="ignore", invalid="ignore"):
                xy = proj[..., :2] / proj[..., 2:]
            for j, i in enumerate(visible.tolist()):
                if clip[j]:
                    poly = _clip(cam[j], *self.frustum)
                    if len(poly) < 3:
                        continue
                    pts = poly @ self.K.T
                    corners = pts[:, :2] / pts[:, 2:]
                else:
                    corners = xy[j]
                self._draw(i, corners, H_inv[j], float(det[j]), image, inv_depth)
        if self.supersample > 1:
            image = cv2.resize(image, (self.camera.width, self.camera.height),
                               interpolation=cv2.INTER_AREA)
        return image

    def _visible(self, R: np.ndarray, C: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Quads facing the camera, near enough and not wholly outside the frustum.

        Returns
        -------
        index : (V,) int ndarray
        cam : (V, 4, 3) float64 ndarray
            Their corners in the camera frame.
        clip : (V,) bool ndarray
            Whether a corner lies outside the frustum (the quad needs clipping).
        """
        rel = self.corners - C                                   # (P, 4, 3)
        facing = self.two_sided | (np.einsum("pj,pj->p", self.normals, -rel[:, 0]) > 0)
        dist = np.sqrt((rel ** 2).sum(axis=2)).min(axis=1)
        cam = rel @ R.T
        normals, offsets = self.frustum
        d = cam @ normals.T - offsets                            # (P, 4, 5)
        outside = d < 0
        inside = ~outside.all(axis=1).any(axis=1)
        index = np.flatnonzero(facing & inside & (dist <= self.max_distance))
        return index, cam[index], outside[index].any(axis=(1, 2))

    def _draw(self, i: int, xy: np.ndarray, H_inv_image: np.ndarray, det: float,
              image: np.ndarray, inv_depth: np.ndarray) -> None:
        """Draw quad ``i`` whose (clipped) outline projects to ``xy``; ``H_inv_image`` maps
        image pixels to its texels."""
        levels = self.pyramids[i]
        h_img, w_img = inv_depth.shape
        (xa, ya), (xb, yb) = xy.min(axis=0).tolist(), xy.max(axis=0).tolist()
        x0, y0 = max(0, math.floor(xa)), max(0, math.floor(ya))
        x1, y1 = min(w_img, math.floor(xb) + 1), min(h_img, math.floor(yb) + 1)
        if x1 <= x0 or y1 <= y0:
            return
        bw, bh = x1 - x0, y1 - y0
        # Bounding-box pixel -> texel: shift the image homography by the box origin.
        H_inv = H_inv_image.copy()
        H_inv[:, 2] += x0 * H_inv_image[:, 0] + y0 * H_inv_image[:, 1]
        local = xy - (x0, y0)
        mask = np.zeros((bh, bw), np.uint8)
        cv2.fillConvexPoly(mask, np.round(local * 16).astype(np.int32), 255, cv2.LINE_8, 4)
        # H^-1 (x, y, 1) = (c, r, 1) / z for H = K R [u | v | origin - C], so its third
        # row gives the inverse depth of the plane at every pixel. Masks stay 8-bit OpenCV
        # images: OpenCV's masked copies are two orders of magnitude faster than numpy's.
        a, b, c = H_inv[2].tolist()
        inv_z = (np.float32(a) * self._xs[:bw])[None, :] + (np.float32(b) * self._ys[:bh]
                                                            + np.float32(c))[:, None]
        region = inv_depth[y0:y1, x0:x1]
        write = cv2.bitwise_and(mask, cv2.compare(inv_z, region, cv2.CMP_GT))
        if not cv2.countNonZero(write):
            return
        lo, hi = _level_range(H_inv, det, local, len(levels))
        if lo == hi:
            tex = _warp(levels[lo], H_inv, (bw, bh))
        else:
            tex = self._warp_levels(levels, H_inv, det, (bw, bh), write, lo, hi)
        if self.planes[i].alpha is not None:
            # (numpy here: OpenCV takes a 4-element array for a scalar.)
            write = cv2.bitwise_and(write, (tex[..., 3] > 127).view(np.uint8) * np.uint8(255))
            tex = cv2.cvtColor(tex, cv2.COLOR_BGRA2BGR)
        cv2.copyTo(tex, write, image[y0:y1, x0:x1])
        cv2.copyTo(inv_z, write, region)

    def _warp_levels(self, levels, H_inv, det, size, write, lo, hi) -> np.ndarray:
        """Warp with a per-pixel mip level (quads seen at grazing angles, the ground).

        The level depends on the pixel only through ``|w|``, the third coordinate of
        ``H^-1 (x, y, 1)``, which is affine in the pixel: level ``L`` covers the band
        ``T(L + 1) < |w| <= T(L)``. Each band's bounding box follows from the row and
        column parts of ``|w|``, so each level is warped only over its own box.
        """
        bw, bh = size
        # w is the inverse depth: positive over the visible quad.
        col = np.float32(H_inv[2, 0]) * self._xs[:bw]
        row = np.float32(H_inv[2, 1]) * self._ys[:bh] + np.float32(H_inv[2, 2])
        out = np.zeros((bh, bw, levels[0][0].shape[2]), np.uint8)
        for lv in range(lo, hi + 1):
            upper = _FLOAT_MAX if lv == 0 else _w_threshold(det, lv)
            lower = 0.0 if lv == len(levels) - 1 else _w_threshold(det, lv + 1)
            # Rows holding some w in (lower, upper]: their range of w is row + [min, max]
            # of the column part; likewise for columns.
            rows = np.flatnonzero((row + col.min() <= upper) & (row + col.max() > lower))
            cols = np.flatnonzero((col + row.min() <= upper) & (col + row.max() > lower))
            if len(rows) == 0 or len(cols) == 0:
                continue
            r0, r1, c0, c1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
            w = col[None, c0:c1] + row[r0:r1, None]
            sel = cv2.bitwise_and(cv2.inRange(w, lower, upper), write[r0:r1, c0:c1])
            if not cv2.countNonZero(sel):
                continue
            shift = np.array([[1.0, 0.0, c0], [0.0, 1.0, r0], [0.0, 0.0, 1.0]])
            part = _warp(levels[lv], H_inv @ shift, (c1 - c0, r1 - r0))
            cv2.copyTo(part, sel, out[r0:r1, c0:c1])
        return out

    def _sky_image(self, R: np.ndarray, size: tuple[int, int]) -> np.ndarray:
        rays = self._sky_rays @ R                 # camera -> world: rows times R
        hs, ws = self.sky.shape[:2]
        bearing = np.degrees(np.arctan2(rays[..., 0], rays[..., 1])) % 360.0
        elevation = np.degrees(np.arcsin(np.clip(rays[..., 2], -1.0, 1.0)))
        map_x = (bearing * (ws / 360.0)).astype(np.float32)
        map_y = np.clip((90.0 - elevation) * ((hs - 1) / (90.0 - SKY_BOTTOM_DEG)), 0, hs - 1)
        small = cv2.remap(self.sky, map_x, map_y.astype(np.float32), cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_WRAP)
        return cv2.resize(small, size, interpolation=cv2.INTER_LINEAR)


def _pixel_rays(camera: Camera, step: int) -> np.ndarray:
    """(h/step, w/step, 3) unit viewing rays (camera frame) of a coarse pixel grid."""
    xs = np.arange(step / 2 - 0.5, camera.width, step)
    ys = np.arange(step / 2 - 0.5, camera.height, step)
    gx, gy = np.meshgrid(xs, ys)
    pix = np.stack([gx, gy, np.ones_like(gx)], axis=-1)
    rays = pix @ np.linalg.inv(camera.matrix).T
    return rays / np.linalg.norm(rays, axis=-1, keepdims=True)


def _pyramid(texture: np.ndarray, alpha: np.ndarray | None) -> list[tuple[np.ndarray, np.ndarray]]:
    """Mip-map levels, each half the size of the previous (INTER_AREA averages 2x2).

    Returns
    -------
    list of (level, to_level)
        The level image (BGR, or BGRA for cut-out quads) and the (3, 3) map from texel
        coordinates of the base texture to those of the level.
    """
    base = np.ascontiguousarray(texture if alpha is None else np.dstack([texture, alpha]))
    levels = [base]
    while min(levels[-1].shape[:2]) > 2:
        prev = levels[-1]
        levels.append(cv2.resize(prev, ((prev.shape[1] + 1) // 2, (prev.shape[0] + 1) // 2),
                                 interpolation=cv2.INTER_AREA))
    out = []
    for level in levels:
        # INTER_AREA maps level texel c to base texels centred on (c + 0.5) * s - 0.5.
        sx, sy = base.shape[1] / level.shape[1], base.shape[0] / level.shape[0]
        to_base = np.array([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5],
                            [0.0, 0.0, 1.0]])
        out.append((level, np.linalg.inv(to_base)))
    return out


_FLOAT_MAX = float(np.finfo(np.float32).max)

_LEVEL_BIAS = 0.25
"""Prefer the sharper level slightly: the 2x supersampling averages once more."""


def _w_threshold(det: float, level: int) -> float:
    """|w| below which the mip level is at least ``level`` (inverse of :func:`_level_of`)."""
    return float((math.sqrt(det) / 2.0 ** (level - _LEVEL_BIAS)) ** (2.0 / 3.0))


def _level_range(H_inv: np.ndarray, det: float, points: np.ndarray,
                 n_levels: int) -> tuple[int, int]:
    """Lowest and highest mip level over a polygon from its vertices: the footprint is
    monotonic in |w|, and w is affine, so its extremes over the polygon lie at vertices."""
    a, b, c = (float(v) for v in H_inv[2])
    ws = [abs(a * x + b * y + c) for x, y in points.tolist()]
    levels = [_level_of(det, w, n_levels) for w in (min(ws), max(ws))]
    return min(levels), max(levels)


def _level_of(det: float, w: float, n_levels: int) -> int:
    footprint = math.sqrt(det) / max(w, 1e-12) ** 1.5
    level = math.floor(math.log2(max(footprint, 1.0)) + _LEVEL_BIAS)
    return min(max(level, 0), n_levels - 1)


def _warp(level: tuple[np.ndarray, np.ndarray], H_inv: np.ndarray,
          size: tuple[int, int]) -> np.ndarray:
    """Sample a pyramid level through the inverse homography (pixel -> base texel)."""
    image, to_level = level
    return cv2.warpPerspective(image, to_level @ H_inv, size,
                               flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                               borderMode=cv2.BORDER_REFLECT_101)


def _clip(poly: np.ndarray, normals: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Clip a convex polygon (camera frame) to the half-spaces ``n . X >= offset``."""
    d = poly @ normals.T - offsets
    for k in np.flatnonzero((d < 0).any(axis=0)):
        if len(poly) == 0:
            break
        dist = poly @ normals[k] - offsets[k]
        out = []
        m = len(poly)
        for j in range(m):
            a, b, da, db = poly[j], poly[(j + 1) % m], dist[j], dist[(j + 1) % m]
            if da >= 0:
                out.append(a)
            if (da >= 0) != (db >= 0):
                out.append(a + (b - a) * (da / (da - db)))
        poly = np.array(out) if out else np.zeros((0, 3))
    return poly
