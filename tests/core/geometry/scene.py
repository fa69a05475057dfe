"""Synthetic scenes with exact geometry: an aerial survey over relief, and a street walk.

Every 3-D point carries a random descriptor; every camera that sees a point observes its
exact projection with the point's descriptor, so ratio-test matching between two images
finds exactly the points both see, and each keypoint's true 3-D point is known
(``point_ids``). Coordinates are the map's: east, north, altitude (m), the ground near
:data:`GROUND_ALT`. Nothing is occluded: a camera sees a point behind a building, which
changes nothing for the geometry the tests check.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from vloc.workers.core.geometry.camera import Intrinsics, focal_from_fov, nadir_rotation, project
from vloc.workers.core.geometry.pairs import PairMatches

WIDTH, HEIGHT = 320, 240
F_TRUE = focal_from_fov(60.0, WIDTH)  # 277.13 px
K_TRUE = Intrinsics(F_TRUE, (WIDTH - 1) / 2.0, (HEIGHT - 1) / 2.0)
"""The principal point at the image's centre in the project's pixels (0 at the centre of
the first pixel), where COLMAP puts it: half a pixel off, and the structure tilts to absorb
it (a metre on the ground from 50 m)."""
GROUND_ALT = 212.0
"""Altitude of the flat ground in the GPS altitude frame (m)."""

CALIBRATED = 2
"""COLMAP's two-view configuration of a pair seen by calibrated cameras
(``pycolmap.TwoViewGeometryConfiguration.CALIBRATED``)."""


def tilted_rotation(theta: float, tilt_deg: float, azimuth: float) -> np.ndarray:
    """A nadir camera with heading ``theta`` tilted by ``tilt_deg`` about a horizontal axis
    of the camera at angle ``azimuth`` from its x axis."""
    axis = np.array([np.cos(azimuth), np.sin(azimuth), 0.0])
    delta = Rotation.from_rotvec(np.radians(tilt_deg) * axis).as_matrix()
    return delta @ nadir_rotation(theta)


def level_rotation(direction: float, pitch_deg: float = 0.0) -> np.ndarray:
    """A camera that does not roll, its optical axis ``direction`` radians anticlockwise
    from east and ``pitch_deg`` above the horizon."""
    p = np.radians(pitch_deg)
    z = np.array([np.cos(direction) * np.cos(p), np.sin(direction) * np.cos(p), np.sin(p)])
    x = np.array([np.sin(direction), -np.cos(direction), 0.0])  # right, level
    return np.stack([x, np.cross(z, x), z])


def tilt_deg(R: np.ndarray) -> float:
    """Angle between the viewing direction and straight down."""
    return float(np.degrees(np.arccos(np.clip(-R[2, 2], -1.0, 1.0))))


def rotation_angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """Angle of the rotation taking ``Ra`` to ``Rb``."""
    return float(np.degrees(Rotation.from_matrix(Ra @ Rb.T).magnitude()))


# -- the world --------------------------------------------------------------------------------

@dataclass(frozen=True)
class Terrain:
    """Ground at :data:`GROUND_ALT` with Gaussian hills and box buildings on it.

    ``hills`` rows are (east, north, height, radius); ``buildings`` rows are
    (east0, north0, east1, north1, height)."""

    hills: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    buildings: np.ndarray = field(default_factory=lambda: np.zeros((0, 5)))

    def ground(self, xy: np.ndarray) -> np.ndarray:
        """Altitude (n,) of the ground, hills included, under each east/north (n, 2)."""
        z = np.full(len(xy), GROUND_ALT)
        for x, y, h, r in self.hills:
            z += h * np.exp(-((xy[:, 0] - x) ** 2 + (xy[:, 1] - y) ** 2) / (2 * r * r))
        return z

    def surface(self, rng: np.random.Generator, lo: np.ndarray, hi: np.ndarray,
                n: int) -> np.ndarray:
        """``n`` points (n, 3) spread over the terrain within east/north ``lo``..``hi``:
        on the ground and the hills, on the roofs, and a share on the buildings' walls."""
        walls = int(0.25 * n) if len(self.buildings) else 0
        xy = rng.uniform(lo, hi, size=(n - walls, 2))
        z = self.ground(xy)
        for x0, y0, x1, y1, h in self.buildings:
            on = (xy[:, 0] >= x0) & (xy[:, 0] <= x1) & (xy[:, 1] >= y0) & (xy[:, 1] <= y1)
            z[on] = self.ground(np.array([[x0, y0]]))[0] + h
        out = [np.column_stack([xy, z])]
        if walls:
            which = rng.integers(0, len(self.buildings), walls)
            for k, (x0, y0, x1, y1, h) in enumerate(self.buildings):
                m = int((which == k).sum())
                side = rng.integers(0, 4, m)
                t = rng.random(m)
                px = np.where(side < 2, x0 + t * (x1 - x0), np.where(side == 2, x0, x1))
                py = np.where(side < 2, np.where(side == 0, y0, y1), y0 + t * (y1 - y0))
                base = self.ground(np.array([[x0, y0]]))[0]
                out.append(np.column_stack([px, py, base + rng.uniform(0.0, h, m)]))
        return np.concatenate(out)


def hilly(lo: np.ndarray, hi: np.ndarray) -> Terrain:
    """Two hills (8 m and 5 m) and three buildings (6 to 14 m) within ``lo``..``hi``."""
    lo = np.asarray(lo, np.float64)
    span = np.asarray(hi, np.float64) - lo

    def at(u: float, v: float) -> np.ndarray:
        return lo + span * [u, v]

    hills = np.array([[*at(0.3, 0.4), 8.0, 0.15 * span.max()],
                      [*at(0.75, 0.7), 5.0, 0.1 * span.max()]])
    buildings = []
    for (u, v), size, h in (((0.55, 0.3), 8.0, 14.0), ((0.2, 0.75), 10.0, 6.0),
                            ((0.8, 0.45), 6.0, 10.0)):
        x, y = at(u, v)
        buildings.append([x - size / 2, y - size / 2, x + size / 2, y + size / 2, h])
    return Terrain(hills, np.array(buildings))


# -- what cameras see -------------------------------------------------------------------------

@dataclass
class Survey:
    """Cameras over a scene of 3-D points, with what each one sees."""

    rotations: np.ndarray  # (N, 3, 3) world -> camera
    centres: np.ndarray  # (N, 3): east, north, altitude
    K: Intrinsics
    points: np.ndarray  # (P, 3) east, north, altitude
    descriptors: np.ndarray  # (P, 128) uint8, one per point
    keypoints: list[np.ndarray]  # per image (K_i, 4) float32: x, y, size, angle
    image_descriptors: list[np.ndarray]  # per image (K_i, 128) uint8
    point_ids: list[np.ndarray]  # per image (K_i,) the point of each keypoint

    @property
    def positions(self) -> np.ndarray:
        return self.centres[:, :2].copy()

    @property
    def altitudes(self) -> np.ndarray:
        return self.centres[:, 2].copy()

    def truth(self, i: int, rows: np.ndarray | None = None) -> np.ndarray:
        """The true 3-D points (k, 3) of image ``i``'s keypoints ``rows`` (all by default)."""
        ids = self.point_ids[i] if rows is None else self.point_ids[i][rows]
        return self.points[ids]

    def __len__(self) -> int:
        return len(self.centres)


def observe(points: np.ndarray, descriptors: np.ndarray, R: np.ndarray, C: np.ndarray,
            K: Intrinsics = K_TRUE, *, size: tuple[int, int] = (WIDTH, HEIGHT),
            max_range: float = np.inf) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Keypoints (K, 4) float32, descriptors and point ids of what camera (R, C) sees of
    ``points`` (P, 3): in front of it, inside the image of ``size`` (width, height),
    nearer than ``max_range``."""
    px = project(R, C, K, points)
    near = np.linalg.norm(points - C, axis=1) < max_range
    seen = np.flatnonzero(np.isfinite(px).all(axis=1) & (px >= -0.5).all(axis=1)
                          & (px[:, 0] < size[0] - 0.5) & (px[:, 1] < size[1] - 0.5) & near)
    kp = np.zeros((len(seen), 4), np.float32)
    kp[:, :2] = px[seen]
    kp[:, 2] = 3.0
    return kp, descriptors[seen], seen


def _seen(rotations: np.ndarray, centres: np.ndarray, K: Intrinsics, points: np.ndarray,
          rng: np.random.Generator, **kwargs) -> Survey:
    descriptors = rng.integers(0, 256, size=(len(points), 128), dtype=np.uint8)
    keypoints, image_desc, ids = [], [], []
    for R, C in zip(rotations, centres, strict=True):
        kp, desc, seen = observe(points, descriptors, R, C, K, **kwargs)
        keypoints.append(kp)
        image_desc.append(desc)
        ids.append(seen)
    return Survey(rotations, centres, K, points, descriptors, keypoints, image_desc, ids)


def survey(rng: np.random.Generator, *, rows: int = 2, cols: int = 4, spacing: float = 18.0,
           height: float = 50.0, max_tilt_deg: float = 3.0, n_points: int = 1500,
           headings: str = "lines", relief: bool = True, roll: bool = False,
           K: Intrinsics = K_TRUE) -> Survey:
    """A lawn-mower survey of ``rows`` x ``cols`` images, ``spacing`` metres apart,
    ``height`` above the flat ground (6 % noise), over hills and buildings (``relief``) or
    flat ground.

    ``headings="lines"`` flies alternate rows in opposite directions (a few degrees of
    yaw noise), ``"random"`` gives every image any heading. Each camera is tilted by up to
    ``max_tilt_deg``: forward or back, as a gimbal that keeps the camera from rolling
    does, or (``roll``) about any horizontal axis. Images are in flight order.
    """
    rotations, centres = [], []
    for r in range(rows):
        for c in range(cols):
            c = c if r % 2 == 0 else cols - 1 - c  # flight order: back along odd rows
            if headings == "lines":
                theta = (0.0 if r % 2 == 0 else np.pi) + np.radians(rng.normal(0.0, 3.0))
            else:
                theta = rng.uniform(-np.pi, np.pi)
            azimuth = rng.uniform(0.0, 2 * np.pi) if roll else np.pi * rng.integers(0, 2)
            rotations.append(tilted_rotation(theta, rng.uniform(0.0, max_tilt_deg), azimuth))
            jitter = spacing / 18.0
            centres.append([c * spacing + rng.normal(0.0, jitter),
                            r * spacing + rng.normal(0.0, jitter),
                            GROUND_ALT + height * (1.0 + rng.uniform(-0.06, 0.06))])
    rotations = np.stack(rotations)
    centres = np.array(centres, np.float64)
    half = height * 0.75
    lo = centres[:, :2].min(axis=0) - half
    hi = centres[:, :2].max(axis=0) + half
    terrain = hilly(lo, hi) if relief else Terrain()
    return _seen(rotations, centres, K, terrain.surface(rng, lo, hi, n_points), rng)


def street(rng: np.random.Generator, *, n: int = 12, step: float = 1.5, eye: float = 1.6,
           look_deg: float = 30.0, width: float = 12.0, n_points: int = 3000,
           K: Intrinsics = K_TRUE) -> Survey:
    """A walk of ``n`` images ``step`` metres apart down a street running east, the camera
    ``eye`` metres above the road, looking ``look_deg`` left of the way ahead (0: straight
    down the street, 90: at the left facade) and a few degrees up.

    The facades stand ``width`` apart, 12 m high, each a row of house fronts set back by
    up to a metre from one another; the road carries a tenth of the points. The walker
    sways sideways by 0.2 m and bobs by 5 cm; cameras see 40 m.
    """
    x = np.arange(n) * step
    centres = np.column_stack([x, rng.normal(0.0, 0.2, n),
                               GROUND_ALT + eye + rng.normal(0.0, 0.05, n)])
    rotations = np.stack([level_rotation(np.radians(look_deg + rng.normal(0.0, 2.0)),
                                         pitch_deg=5.0 + rng.normal(0.0, 1.0))
                          for _ in range(n)])
    lo, hi = -15.0, x[-1] + 45.0
    road = n_points // 10
    facade = (n_points - road) // 2
    parts = [np.column_stack([rng.uniform(lo, hi, road), rng.uniform(-width / 2, width / 2, road),
                              np.full(road, GROUND_ALT)])]
    fronts = np.arange(lo, hi + 6.0, 6.0)  # a house front every 6 m
    for side in (-1.0, 1.0):
        setback = rng.uniform(0.0, 1.0, len(fronts))
        e = rng.uniform(lo, hi, facade)
        y = side * (width / 2 + setback[np.searchsorted(fronts, e)])
        parts.append(np.column_stack([e, y, GROUND_ALT + rng.uniform(0.0, 12.0, facade)]))
    return _seen(rotations, centres, K, np.concatenate(parts), rng, max_range=40.0)


def exact_pairs(s: Survey, *, min_common: int = 15, max_per_pair: int | None = None,
                rng: np.random.Generator | None = None) -> list[PairMatches]:
    """Verified matches of every pair of images that share at least ``min_common`` points:
    the keypoints of the points both see (``max_per_pair`` of them drawn by ``rng`` where
    given), as :func:`~vloc.workers.core.geometry.pairs.match_pair` would verify them."""
    out = []
    for a in range(len(s)):
        for b in range(a + 1, len(s)):
            _, ia, ib = np.intersect1d(s.point_ids[a], s.point_ids[b], return_indices=True)
            if len(ia) < min_common:
                continue
            if max_per_pair is not None and len(ia) > max_per_pair:
                keep = np.sort(rng.choice(len(ia), size=max_per_pair, replace=False))
                ia, ib = ia[keep], ib[keep]
            out.append(PairMatches(a, b, np.column_stack([ia, ib]).astype(np.int64),
                                   CALIBRATED))
    return out


def similarity_residuals(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Each point's distance left between point sets ``a`` and ``b`` once the best
    similarity takes one onto the other (Umeyama)."""
    ma, mb = a.mean(axis=0), b.mean(axis=0)
    u, d, vt = np.linalg.svd((b - mb).T @ (a - ma))
    sign = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    R = u @ sign @ vt
    scale = np.trace(np.diag(d) @ sign) / np.sum((a - ma) ** 2)
    return np.linalg.norm(scale * (a - ma) @ R.T + mb - b, axis=1)


def similarity_residual(a: np.ndarray, b: np.ndarray) -> float:
    """The largest of :func:`similarity_residuals`."""
    return float(similarity_residuals(a, b).max())
