"""What a device may report about a frame besides its pixels.

Every field is optional: a device that sends nothing gets the purely visual estimate.
Values are checked here once (finite, in range) so that every entry point (HTTP, the
client, ``vloc replay``, ``vloc eval``) refuses the same inputs with the same reason.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

#: The fields of :class:`FrameMetadata`, as they are named in data set CSVs and over HTTP.
METADATA_FIELDS = ("heading_deg", "heading_accuracy_deg", "altitude_m", "gps_lat", "gps_lon",
                   "gps_accuracy_m", "velocity_east", "velocity_north")

#: The kinds of metadata a localiser can use, as named by ``--use-metadata``.
METADATA_KINDS = ("heading", "gps", "altitude", "velocity")


ACCURACY_RANGES = {"heading_accuracy_deg": (0.01, 180.0), "gps_accuracy_m": (0.01, 10_000.0)}
"""Accuracies a report can state: finer is no real sensor, and squaring it underflows; a
GNSS fix vaguer than 10 km carries nothing, and squaring a huge one overflows."""


@dataclass(frozen=True, slots=True)
class FrameMetadata:
    """Optional per-frame reports from the device's other sensors.

    Attributes
    ----------
    heading_deg : float or None
        Compass bearing of the frame's top edge, degrees clockwise from north, [0, 360).
    heading_accuracy_deg : float or None
        Its standard deviation in degrees (> 0); a default is assumed when absent.
    altitude_m : float or None
        Altitude above the WGS84 ellipsoid or mean sea level as the device reports it.
    gps_lat, gps_lon : float or None
        A GNSS fix, WGS84 degrees; both or neither.
    gps_accuracy_m : float or None
        The fix's horizontal accuracy (one standard deviation, metres, > 0). A fix without
        it is taken at :data:`DEFAULT_GPS_ACCURACY_M`.
    velocity_east, velocity_north : float or None
        Ground velocity from odometry or the autopilot, metres per second; both or neither.
    """

    heading_deg: float | None = None
    heading_accuracy_deg: float | None = None
    altitude_m: float | None = None
    gps_lat: float | None = None
    gps_lon: float | None = None
    gps_accuracy_m: float | None = None
    velocity_east: float | None = None
    velocity_north: float | None = None

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if v is not None and not math.isfinite(v):
                raise ValueError(f"{f.name} must be a finite number")
        if self.heading_deg is not None and not 0.0 <= self.heading_deg < 360.0:
            raise ValueError("heading_deg must be in [0, 360)")
        for name, (low, high) in ACCURACY_RANGES.items():
            v = getattr(self, name)
            if v is not None and v <= 0.0:
                raise ValueError(f"{name} must be positive")
            if v is not None and not low <= v <= high:
                raise ValueError(f"{name} must be in [{low:g}, {high:g}]")
        if (self.gps_lat is None) != (self.gps_lon is None):
            raise ValueError("gps_lat and gps_lon come together")
        if self.gps_lat is not None and not -90.0 <= self.gps_lat <= 90.0:
            raise ValueError("gps_lat must be in [-90, 90]")
        if self.gps_lon is not None and not -180.0 <= self.gps_lon <= 180.0:
            raise ValueError("gps_lon must be in [-180, 180]")
        if self.gps_accuracy_m is not None and self.gps_lat is None:
            raise ValueError("gps_accuracy_m needs gps_lat and gps_lon")
        if self.heading_accuracy_deg is not None and self.heading_deg is None:
            raise ValueError("heading_accuracy_deg needs heading_deg")
        if self.altitude_m is not None and not -500.0 <= self.altitude_m <= 10_000.0:
            raise ValueError("altitude_m must be in [-500, 10000]")
        if (self.velocity_east is None) != (self.velocity_north is None):
            raise ValueError("velocity_east and velocity_north come together")
        if self.velocity_east is not None and math.hypot(self.velocity_east,
                                                         self.velocity_north) > 150.0:
            raise ValueError("velocity must be at most 150 m/s")

    @property
    def has_gps(self) -> bool:
        return self.gps_lat is not None

    @property
    def has_heading(self) -> bool:
        return self.heading_deg is not None

    @property
    def has_velocity(self) -> bool:
        return self.velocity_east is not None

    def kinds(self) -> tuple[str, ...]:
        """Which of :data:`METADATA_KINDS` this frame carries."""
        present = {"heading": self.has_heading, "gps": self.has_gps,
                   "altitude": self.altitude_m is not None, "velocity": self.has_velocity}
        return tuple(k for k in METADATA_KINDS if present[k])

    def only(self, kinds: tuple[str, ...] | set[str]) -> FrameMetadata:
        """A copy keeping only the named kinds (``vloc eval --use-metadata``)."""
        unknown = set(kinds) - set(METADATA_KINDS)
        if unknown:
            raise ValueError(f"unknown metadata kinds: {sorted(unknown)}")
        keep = {
            "heading": ("heading_deg", "heading_accuracy_deg"),
            "gps": ("gps_lat", "gps_lon", "gps_accuracy_m"),
            "altitude": ("altitude_m",),
            "velocity": ("velocity_east", "velocity_north"),
        }
        names = {n for k in kinds for n in keep[k]}
        return FrameMetadata(**{n: v for n, v in asdict(self).items() if n in names})

    def to_dict(self) -> dict:
        """The fields that are set (what goes over the wire)."""
        return {k: v for k, v in asdict(self).items() if v is not None}

    @classmethod
    def from_dict(cls, data: dict | None) -> FrameMetadata | None:
        """From :meth:`to_dict`'s form; None or an empty dict gives None."""
        if not data:
            return None
        names = {f.name for f in fields(cls)}
        unknown = set(data) - names
        if unknown:
            raise ValueError(f"unknown metadata fields: {sorted(unknown)}")
        return cls(**{k: (None if v is None else float(v)) for k, v in data.items()})


#: Horizontal accuracy assumed for a GPS fix that does not state one, metres.
DEFAULT_GPS_ACCURACY_M = 10.0
#: Accuracy assumed for a compass heading that does not state one, degrees.
DEFAULT_HEADING_ACCURACY_DEG = 15.0
