"""A map's camera geometry, packed beside its features.

Arrays (saved as ``geometry_*.npy`` in the map folder, memory-mappable like the rest)
------------------------------------------------------------------------------------
rotations : (N, 3, 3) float64
    World -> camera rotation of each map image; NaN where not reconstructed.
centres : (N, 3) float64
    Camera centre (east, north, height above the ground plane); NaN where not reconstructed.
intrinsics : (3,) float64
    f, cx, cy in pixels at the working resolution.
ground[kind] : (K, 2) float32
    East/north on the ground of every keypoint of the map's local-feature set ``kind``
    (``"sift"``, row-aligned with ``MapData.sift_keypoints``); NaN where unknown.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .camera import Intrinsics, backproject_to_ground
from .reconstruct import PlaneReconstruction


@dataclass
class MapGeometry:
    rotations: np.ndarray
    centres: np.ndarray
    intrinsics: Intrinsics
    ground_alt: float
    residual_px: float
    gps_rms: float
    ground: dict[str, np.ndarray] = field(default_factory=dict)

    @classmethod
    def from_reconstruction(cls, rec: PlaneReconstruction) -> MapGeometry:
        return cls(rec.rotations, rec.centres, rec.intrinsics, rec.ground_alt,
                   rec.residual_px, rec.gps_rms)

    @property
    def reconstructed(self) -> np.ndarray:
        """(N,) bool: which map images have a camera pose."""
        return np.isfinite(np.asarray(self.centres)[:, 0])

    def height_range(self) -> tuple[float, float]:
        """Plausible heights of a frame's camera: the map cameras' range, widened."""
        h = np.asarray(self.centres)[self.reconstructed, 2]
        if len(h) == 0:
            return (0.0, 0.0)
        return float(0.5 * h.min()), float(1.6 * h.max())

    def add_ground(self, kind: str, keypoints: np.ndarray, offsets: np.ndarray) -> None:
        """Place the keypoints of local-feature set ``kind`` on the ground.

        Parameters
        ----------
        keypoints : (K, >=2) float ndarray
            Pixels in the first two columns; image ``i`` owns rows
            ``offsets[i]:offsets[i + 1]``.
        offsets : (N + 1,) int ndarray
        """
        out = np.full((len(keypoints), 2), np.nan, dtype=np.float32)
        centres = np.asarray(self.centres)
        for i in np.flatnonzero(self.reconstructed):
            a, b = int(offsets[i]), int(offsets[i + 1])
            if b > a:
                out[a:b] = backproject_to_ground(
                    np.asarray(self.rotations[i]), centres[i], self.intrinsics,
                    np.asarray(keypoints[a:b, :2], np.float64))
        self.ground[kind] = out

    # -- persistence ----------------------------------------------------------------------

    def save(self, folder: Path) -> None:
        np.save(folder / "geometry_rotations.npy", np.asarray(self.rotations, np.float64))
        np.save(folder / "geometry_centres.npy", np.asarray(self.centres, np.float64))
        for kind, arr in self.ground.items():
            np.save(folder / f"geometry_ground_{kind}.npy", np.asarray(arr, np.float32))
        k = self.intrinsics
        meta = {"f": k.f, "cx": k.cx, "cy": k.cy, "ground_alt": _num(self.ground_alt),
                "residual_px": _num(self.residual_px), "gps_rms": _num(self.gps_rms),
                "ground": sorted(self.ground)}
        (folder / "geometry.json").write_text(json.dumps(meta))

    @classmethod
    def load(cls, folder: Path, *, mmap: bool = True) -> MapGeometry | None:
        """The geometry saved in ``folder``, or None for a map saved without one."""
        path = folder / "geometry.json"
        if not path.exists():
            return None
        meta = json.loads(path.read_text())
        mode = "r" if mmap else None
        ground = {kind: np.load(folder / f"geometry_ground_{kind}.npy", mmap_mode=mode)
                  for kind in meta["ground"]}
        return cls(np.load(folder / "geometry_rotations.npy", mmap_mode=mode),
                   np.load(folder / "geometry_centres.npy", mmap_mode=mode),
                   Intrinsics(meta["f"], meta["cx"], meta["cy"]),
                   _float(meta["ground_alt"]), _float(meta["residual_px"]),
                   _float(meta["gps_rms"]), ground)


def _num(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def _float(x: float | None) -> float:
    return float("nan") if x is None else float(x)
