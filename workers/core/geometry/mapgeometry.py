"""A map's camera geometry, packed beside its features.

Arrays (saved as ``geometry_*.npy`` in the map folder, memory-mappable like the rest)
------------------------------------------------------------------------------------
rotations : (N, 3, 3) float64
    World -> camera rotation of each map image; NaN where not reconstructed.
centres : (N, 3) float64
    Camera centre (east, north, altitude in the frame of the GPS altitudes); NaN where not
    reconstructed.
intrinsics, k1
    f, cx, cy in pixels at the working resolution, and the radial distortion (OpenCV's
    first coefficient).
points[kind] : (K, 3) float32
    The 3-D point (east, north, altitude) every keypoint of the map's local-feature set
    ``kind`` sees (``"sift"``, row-aligned with ``MapData.sift_keypoints``; ``"orb"``);
    NaN where unknown.
self_check : dict
    What the map measured of itself at build time (:mod:`workers.core.selfcheck`).
digests : (N, 16) uint8
    What each image's keypoints' 3-D points were worked out from, hashed
    (:func:`structure_digests`): an update takes up the points of an image whose digest
    and keypoints are the revision before's (:func:`workers.core.carryover.known_points`).
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial import cKDTree

from ..rowchunks import load_chunked
from .camera import Intrinsics

DEPTH_RADIUS_PX: float = 20.0
"""A stored keypoint takes its depth from the reconstructed tie points of its image within
this many pixels (working resolution)."""

DEPTH_NEIGHBOURS: int = 4
"""... the median depth of at most this many of the nearest."""

FLAT_VIEW: float = 0.05
"""A keypoint with no reconstructed tie point near it meets the plane fitted through its
image's 3-D points, where they lie within this share of their depth from that plane (a
survey's view of open ground); elsewhere (streets, buildings) it gets no point."""

NADIR_SPREAD_DEG: float = 15.0
"""Maps whose cameras all look within this of their mean direction, more down than ahead (a
survey flown with a fixed gimbal), get a prior on a frame's viewing direction; a street
walked one way, whose cameras look one way too, does not: a frame may turn there."""

EXACT_PX: float = 1.0
"""A stored keypoint this close to a reconstructed tie point (working-resolution pixels) is
that tie point, and takes its 3-D point."""

FORMAT = 2
"""Version of the saved geometry: 2 is the structure-from-motion geometry with 3-D points;
1 (no version) was a ground plane, read as points on it. A change to how
:meth:`MapGeometry.add_points` works the points out bumps it too: it is part of every
image's digest (:func:`structure_digests`), which an update's points are taken up by."""


@dataclass
class MapGeometry:
    rotations: np.ndarray
    centres: np.ndarray
    intrinsics: Intrinsics
    k1: float = 0.0
    residual_px: float = math.nan
    gps_rms: float = math.nan
    gps_rms_v: float = math.nan
    models: int = 1
    points: dict[str, np.ndarray] = field(default_factory=dict)
    self_check: dict = field(default_factory=dict)
    digests: np.ndarray | None = None
    # what every frame's registration asks of the map's cameras, worked out once
    _memo: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __setattr__(self, name: str, value) -> None:
        # new cameras: what was worked out from the old ones no longer holds
        if name in ("rotations", "centres"):
            self.__dict__.get("_memo", {}).clear()
        super().__setattr__(name, value)

    @classmethod
    def from_structure(cls, structure) -> MapGeometry:
        """The geometry of a :class:`~.models.Structure` (its points added by
        :meth:`add_points`)."""
        return cls(structure.rotations, structure.centres, structure.intrinsics,
                   structure.k1, structure.residual_px, structure.gps_rms_h,
                   structure.gps_rms_v, structure.models)

    @property
    def reconstructed(self) -> np.ndarray:
        """(N,) bool, read-only: which map images have a camera pose (worked out once: a
        global step asks it of every frame)."""
        if "placed" not in self._memo:
            placed = np.isfinite(np.asarray(self.centres)[:, 0])
            placed.setflags(write=False)
            self._memo["placed"] = placed
        return self._memo["placed"]

    @property
    def base_sigma(self) -> float:
        """Standard deviation (m) of the map's own registrations, from its self-check; 2 m
        where it has none."""
        sigma = self.self_check.get("sigma_m")
        return float(sigma) if sigma is not None and math.isfinite(sigma) else 2.0

    @property
    def distortion(self) -> np.ndarray:
        """OpenCV's distortion coefficients (k1, k2, p1, p2)."""
        return np.array([self.k1, 0.0, 0.0, 0.0])

    def altitude_range(self) -> tuple[float, float]:
        """Plausible altitudes of a frame's camera: the map cameras', widened by half their
        span and at least 20 m either way."""
        if "altitudes" not in self._memo:
            self._memo["altitudes"] = self._altitude_range()
        return self._memo["altitudes"]

    def _altitude_range(self) -> tuple[float, float]:
        z = np.asarray(self.centres)[self.reconstructed, 2]
        if len(z) == 0:
            return (0.0, 0.0)
        margin = max(20.0, 0.5 * float(z.max() - z.min()))
        return float(z.min()) - margin, float(z.max()) + margin

    def view_prior(self) -> tuple[np.ndarray, float] | None:
        """The map cameras' mean viewing direction and its spread (degrees, at least 5)
        where they all look within :data:`NADIR_SPREAD_DEG` of it; None otherwise (a
        street-level map, a survey that turns its camera)."""
        if "view" not in self._memo:
            self._memo["view"] = self._view_prior()
        return self._memo["view"]

    def _view_prior(self) -> tuple[np.ndarray, float] | None:
        R = np.asarray(self.rotations)[self.reconstructed]
        if len(R) < 3:
            return None
        axes = R[:, 2, :]
        mean = axes.mean(axis=0)
        mean /= np.linalg.norm(mean)
        if -mean[2] < np.cos(np.radians(45.0)):
            return None
        angles = np.degrees(np.arccos(np.clip(axes @ mean, -1.0, 1.0)))
        if np.percentile(angles, 95) > NADIR_SPREAD_DEG:
            return None
        return mean, max(5.0, float(np.sqrt(np.mean(angles ** 2))))

    def add_points(self, kind: str, keypoints: np.ndarray, offsets: np.ndarray,
                   seen: Sequence[tuple[np.ndarray, np.ndarray]], *,
                   known: dict[int, np.ndarray] | None = None) -> None:
        """Give the keypoints of local-feature set ``kind`` their 3-D points.

        A stored keypoint on a reconstructed tie point of its image (:data:`EXACT_PX`) takes
        that tie point's 3-D point; one near some takes their median depth along its own ray
        (:data:`DEPTH_RADIUS_PX`, :data:`DEPTH_NEIGHBOURS`), a local interpolation of the
        surface; one with none near it meets the plane of its image's points where the image
        sees one (:data:`FLAT_VIEW`).

        Parameters
        ----------
        keypoints : (K, >=2) float ndarray
            Pixels in the first two columns; image ``i`` owns rows
            ``offsets[i]:offsets[i + 1]``.
        offsets : (N + 1,) int ndarray
        seen : sequence of ((k_i, 2) pixels, (k_i, 3) points), one per map image
            The reconstructed tie points of each image and their 3-D points, read only for
            the images ``known`` does not give.
        known : dict, optional
            Image -> its keypoints' 3-D points ((k_i, 3) float32), worked out before from
            the same inputs (:func:`workers.core.carryover.known_points`): taken as they are.
        """
        out = np.full((len(keypoints), 3), np.nan, dtype=np.float32)
        centres, rotations = np.asarray(self.centres), np.asarray(self.rotations)
        known = {} if known is None else known
        for i in np.flatnonzero(self.reconstructed):
            a, b = int(offsets[i]), int(offsets[i + 1])
            if i in known:
                out[a:b] = known[i]
                continue
            px, xyz = seen[i]
            if b <= a or len(px) < 3:
                continue
            R, C = rotations[i], centres[i]
            depth = (np.asarray(xyz, np.float64) - C) @ R[2]
            dist, near = cKDTree(px).query(np.asarray(keypoints[a:b, :2], np.float64),
                                           k=min(DEPTH_NEIGHBOURS, len(px)),
                                           distance_upper_bound=DEPTH_RADIUS_PX)
            dist, near = dist.reshape(b - a, -1), near.reshape(b - a, -1)
            found = np.isfinite(dist)
            d = np.where(found, depth[np.minimum(near, len(px) - 1)], np.nan)
            ok = found.any(axis=1)
            z = np.full(b - a, np.nan)
            z[ok] = np.nanmedian(d[ok], axis=1)
            rays = self.rays(np.asarray(keypoints[a:b, :2], np.float64))
            if not ok.all():
                z[~ok] = _plane_depths(np.asarray(xyz, np.float64), R, C, rays[~ok], depth)
            done = np.isfinite(z)
            out[a:b][done] = (C + (z[done, None] * rays[done]) @ R).astype(np.float32)
            same = dist[:, 0] <= EXACT_PX
            out[a:b][same] = np.asarray(xyz, np.float64)[near[same, 0]].astype(np.float32)
        self.points[kind] = out

    def rays(self, pixels: np.ndarray) -> np.ndarray:
        """Pixels (n, 2) -> undistorted camera rays ``(x, y, 1)`` (n, 3)."""
        K = self.intrinsics.matrix
        norm = cv2.undistortPoints(np.asarray(pixels, np.float64).reshape(-1, 1, 2), K,
                                   self.distortion).reshape(-1, 2)
        return np.column_stack([norm, np.ones(len(norm))])

    # -- persistence ----------------------------------------------------------------------

    def save(self, folder: Path, *, save_rows=None) -> None:
        """Write the geometry to ``folder``; ``save_rows(kind, stem, points)``, where given,
        saves each kind's points in chunks and returns their list
        (:func:`workers.core.rowchunks.save_chunked`)."""
        np.save(folder / "geometry_rotations.npy", np.asarray(self.rotations, np.float64))
        np.save(folder / "geometry_centres.npy", np.asarray(self.centres, np.float64))
        if self.digests is not None:
            np.save(folder / "geometry_digests.npy", np.asarray(self.digests, np.uint8))
        chunks = {}
        for kind, arr in self.points.items():
            stem = f"geometry_points_{kind}"
            if save_rows is None:
                np.save(folder / f"{stem}.npy", np.asarray(arr, np.float32))
            else:
                chunks[kind] = save_rows(kind, stem, np.asarray(arr, np.float32))
        k = self.intrinsics
        meta = {"format": FORMAT, "f": k.f, "cx": k.cx, "cy": k.cy, "k1": self.k1,
                "residual_px": _num(self.residual_px), "gps_rms": _num(self.gps_rms),
                "gps_rms_v": _num(self.gps_rms_v), "models": self.models,
                "points": sorted(self.points), "self_check": self.self_check}
        if chunks:
            meta["point_chunks"] = chunks
        (folder / "geometry.json").write_text(json.dumps(meta))

    @classmethod
    def load(cls, folder: Path, *, mmap: bool = True) -> MapGeometry | None:
        """The geometry saved in ``folder``, or None for a map saved without one."""
        path = folder / "geometry.json"
        if not path.exists():
            return None
        meta = json.loads(path.read_text())
        mode = "r" if mmap else None
        rotations = np.load(folder / "geometry_rotations.npy", mmap_mode=mode)
        centres = np.load(folder / "geometry_centres.npy", mmap_mode=mode)
        K = Intrinsics(meta["f"], meta["cx"], meta["cy"])
        if meta.get("format", 1) < 2:
            return cls._from_plane(folder, meta, rotations, centres, K)
        chunks = meta.get("point_chunks", {})
        points = {kind: load_chunked(folder, chunks[kind], mmap=mmap) if kind in chunks
                  else np.load(folder / f"geometry_points_{kind}.npy", mmap_mode=mode)
                  for kind in meta["points"]}
        # read by the next build only: mapped, a session's load never touches them (none
        # for a map packed before they were kept)
        digests = folder / "geometry_digests.npy"
        return cls(rotations, centres, K, float(meta.get("k1", 0.0)),
                   _float(meta["residual_px"]), _float(meta["gps_rms"]),
                   _float(meta.get("gps_rms_v")), int(meta.get("models", 1)), points,
                   dict(meta.get("self_check") or {}),
                   np.load(digests, mmap_mode=mode) if digests.is_file() else None)

    @classmethod
    def _from_plane(cls, folder: Path, meta: dict, rotations: np.ndarray,
                    centres: np.ndarray, K: Intrinsics) -> MapGeometry:
        """A map packed with the ground-plane geometry: its ground points at the plane's
        altitude, its camera heights as altitudes."""
        ground_alt = _float(meta.get("ground_alt"))
        ground_alt = 0.0 if not math.isfinite(ground_alt) else ground_alt
        points = {}
        for kind in meta.get("ground", []):
            xy = np.load(folder / f"geometry_ground_{kind}.npy")
            points[kind] = np.column_stack(
                [xy, np.full(len(xy), ground_alt, np.float32)]).astype(np.float32)
        centres = np.array(centres, np.float64)
        centres[:, 2] += ground_alt
        return cls(np.asarray(rotations), centres, K, 0.0, _float(meta.get("residual_px")),
                   _float(meta.get("gps_rms")), points=points)


def structure_digests(structure) -> np.ndarray:
    """(N, 16) uint8: what :meth:`MapGeometry.add_points` works each image's keypoints'
    3-D points out from, hashed: its pose, its reconstructed tie points (by index: an
    image's tie points never change, its file does not) and their 3-D points, the map's
    intrinsics and distortion, and the depth rules' settings; zeros for an image without a
    pose. A :class:`~.models.Structure` is given."""
    k = structure.intrinsics
    common = np.array([FORMAT, k.f, k.cx, k.cy, structure.k1, DEPTH_RADIUS_PX,
                       DEPTH_NEIGHBOURS, FLAT_VIEW, EXACT_PX], np.float64).tobytes()
    out = np.zeros((len(structure.centres), 16), np.uint8)
    for i in np.flatnonzero(structure.placed):
        h = hashlib.blake2b(common, digest_size=16)
        for part in (structure.rotations[i], structure.centres[i], structure.observations[i],
                     structure.points[i]):
            h.update(np.ascontiguousarray(part).tobytes())
        out[i] = np.frombuffer(h.digest(), np.uint8)
    return out


def _plane_depths(xyz: np.ndarray, R: np.ndarray, C: np.ndarray, rays: np.ndarray,
                  depth: np.ndarray) -> np.ndarray:
    """Depths along camera ``rays`` (n, 3) to the plane through ``xyz`` (its image's 3-D
    points, at ``depth``), NaN where the points are no plane (:data:`FLAT_VIEW`) or a ray
    misses it."""
    out = np.full(len(rays), np.nan)
    if len(xyz) < 10:
        return out
    centre = xyz.mean(axis=0)
    _, sv, vt = np.linalg.svd(xyz - centre, full_matrices=False)
    normal = vt[2]
    if sv[2] / np.sqrt(len(xyz)) > FLAT_VIEW * float(np.median(depth)):
        return out
    dirs = rays @ R  # camera rays in the world (R.T @ ray per row)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = ((centre - C) @ normal) / (dirs @ normal)
    t[~(t > 0)] = np.nan
    # t scales the world direction of (x, y, 1): that is the depth along the optical axis
    return t


def _num(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def _float(x: float | None) -> float:
    return float("nan") if x is None else float(x)
