"""Local east-north frames and WGS84.

Every map has a local tangent plane (east, north, up) at a reference point; all metric
work happens there and WGS84 is converted at the edges. pymap3d does the geodesy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pymap3d


@dataclass(frozen=True, slots=True)
class GeoOrigin:
    """Reference point of a local east-north-up frame (WGS84 degrees, metres)."""

    lat: float
    lon: float
    alt: float = 0.0

    def __post_init__(self) -> None:
        check_lat_lon(self.lat, self.lon)

    def to_local(self, lat, lon, alt=None) -> tuple[np.ndarray, np.ndarray]:
        """WGS84 -> (east, north) metres. Accepts scalars or arrays."""
        lat = np.asarray(lat, dtype=np.float64)
        lon = np.asarray(lon, dtype=np.float64)
        h = np.full_like(lat, self.alt) if alt is None else np.asarray(alt, dtype=np.float64)
        e, n, _ = pymap3d.geodetic2enu(lat, lon, h, self.lat, self.lon, self.alt)
        return np.asarray(e, dtype=np.float64), np.asarray(n, dtype=np.float64)

    def to_wgs84(self, east, north, up=0.0) -> tuple[np.ndarray, np.ndarray]:
        """(east, north) metres -> WGS84 (lat, lon) degrees."""
        lat, lon, _ = pymap3d.enu2geodetic(
            np.asarray(east, dtype=np.float64), np.asarray(north, dtype=np.float64),
            np.asarray(up, dtype=np.float64), self.lat, self.lon, self.alt,
        )
        return np.asarray(lat, dtype=np.float64), np.asarray(lon, dtype=np.float64)

    @classmethod
    def centroid_of(cls, lat, lon, alt=None) -> GeoOrigin:
        """An origin at the mean position of a set of points."""
        lat = np.asarray(lat, dtype=np.float64)
        lon = np.asarray(lon, dtype=np.float64)
        a = 0.0 if alt is None or len(np.atleast_1d(alt)) == 0 else float(np.mean(alt))
        return cls(float(np.mean(lat)), float(np.mean(lon)), a)


def check_lat_lon(lat: float, lon: float) -> None:
    """Raise ValueError for NaN, infinite or out-of-range WGS84 coordinates."""
    for name, value, bound in (("lat", lat, 90.0), ("lon", lon, 180.0)):
        v = float(value)
        if not math.isfinite(v):
            raise ValueError(f"{name} must be a finite number, got {value!r}")
        if abs(v) > bound:
            raise ValueError(f"{name} must be within +-{bound:g} degrees, got {v:g}")


def local_frame(lats, lons, alts, origin: GeoOrigin | None = None,
                ) -> tuple[GeoOrigin, np.ndarray, np.ndarray]:
    """The local frame a map of these images is packed in (``origin``, by default at their
    centroid), their (N, 2) east/north in it and their (N,) altitudes (NaN where None)."""
    lat = np.asarray(lats, np.float64)
    lon = np.asarray(lons, np.float64)
    alt = np.array([np.nan if a is None else a for a in alts], np.float64)
    if origin is None:
        origin = GeoOrigin.centroid_of(lat, lon, np.where(np.isfinite(alt), alt, 0.0))
    east, north = origin.to_local(lat, lon)
    return origin, np.stack([np.atleast_1d(east), np.atleast_1d(north)], axis=1), alt
