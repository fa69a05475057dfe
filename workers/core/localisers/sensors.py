"""What a device's other sensors add to a filter step (:mod:`workers.core.metadata`).

A GPS fix is a position measurement of its stated accuracy, used only when it lies within
the gate of the predicted cloud: a chi-square test at :data:`GPS_GATE_CHI2` on the cloud's
covariance, the motion since and the fix's own accuracy. A jumping or spoofed fix is then
ignored and reported ``rejected``; a lost filter (a cloud spread over the map) accepts any
fix. A compass heading vetoes registrations that disagree with it
(:data:`HEADING_GATE_SIGMAS`); a reported velocity moves the cloud as the tracked drift does.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geo import GeoOrigin
from ..metadata import DEFAULT_GPS_ACCURACY_M, DEFAULT_HEADING_ACCURACY_DEG, FrameMetadata
from ..pf.filter import CloudStats
from ..pf.measurement import Position
from .refine import Refinement

GPS_GATE_CHI2: float = 13.8
"""Squared Mahalanobis distance beyond which a GPS fix disagrees with the predicted cloud:
the 99.9 % point of the chi-square distribution with two degrees of freedom."""

GPS_OUTLIER: float = 0.01
"""Probability that a GPS fix inside the gate is still wrong (multipath): its floor."""

HEADING_GATE_SIGMAS: float = 3.0
"""A registration whose heading differs from the compass by more than this many combined
standard deviations is taken for a wrong solve and not used."""


@dataclass(frozen=True)
class Sensors:
    """What a frame's metadata contributes to its step.

    Attributes
    ----------
    used : tuple of str
        The kinds of metadata the step took into account.
    positions : tuple of Position
        Position measurements (a GPS fix that passed its gate).
    gps_gate : {"", "used", "rejected"}
    heading : (float, float) or None
        Compass heading and its standard deviation (degrees).
    velocity : (2,) float ndarray or None
        East/north velocity (m/s).
    """

    used: tuple[str, ...] = ()
    positions: tuple[Position, ...] = ()
    gps_gate: str = ""
    heading: tuple[float, float] | None = None
    velocity: np.ndarray | None = None


def read_sensors(metadata: FrameMetadata, origin: GeoOrigin, cloud: CloudStats,
                 motion_sigma: float) -> Sensors:
    """The step's :class:`Sensors` from the frame's metadata.

    Parameters
    ----------
    metadata : FrameMetadata
    origin : GeoOrigin
        The map's local frame.
    cloud : CloudStats
        The cloud as the last step left it.
    motion_sigma : float
        Per-axis motion sigma (m) until this frame.
    """
    used: list[str] = []
    positions: list[Position] = []
    gate = ""
    if metadata.has_gps:
        used.append("gps")
        acc = metadata.gps_accuracy_m or DEFAULT_GPS_ACCURACY_M
        east, north = origin.to_local(metadata.gps_lat, metadata.gps_lon)
        fix = np.array([float(east), float(north)])
        cov = np.asarray(cloud.cov) + (motion_sigma ** 2 + acc ** 2) * np.eye(2)
        d = fix - np.asarray(cloud.mean)
        if float(d @ np.linalg.solve(cov, d)) <= GPS_GATE_CHI2:
            positions.append(Position("gps", fix, acc, GPS_OUTLIER))
            gate = "used"
        else:
            gate = "rejected"
    heading = None
    if metadata.has_heading:
        used.append("heading")
        heading = (metadata.heading_deg,
                   metadata.heading_accuracy_deg or DEFAULT_HEADING_ACCURACY_DEG)
    velocity = None
    if metadata.has_velocity:
        used.append("velocity")
        velocity = np.array([metadata.velocity_east, metadata.velocity_north])
    return Sensors(tuple(used), tuple(positions), gate, heading, velocity)


def heading_agrees(fix: Refinement, compass: tuple[float, float] | None) -> bool:
    """Whether a fix's camera heading agrees with the compass (True where either is
    unknown)."""
    if compass is None or fix.heading_deg is None:
        return True
    diff = abs((fix.heading_deg - compass[0] + 180.0) % 360.0 - 180.0)
    sigma = float(np.hypot(compass[1], fix.heading_sigma_deg or 0.0))
    return diff <= HEADING_GATE_SIGMAS * sigma
