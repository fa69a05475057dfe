"""What a localiser returns for each frame."""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum


class Status(StrEnum):
    INITIALISING = "initialising"
    TRACKING = "tracking"
    LOST = "lost"


@dataclass(frozen=True, slots=True)
class Estimate:
    """One pose estimate.

    Attributes
    ----------
    x, y : float
        East and north in metres, in the map's local frame.
    lat, lon : float
        The same position in WGS84 degrees.
    sigma_x, sigma_y : float
        Weighted standard deviations of the particle cloud (Weiss eq. 2), metres.
    cov : tuple of 4 floats
        Row-major 2x2 covariance of the position (metres squared).
    feature : str
        Feature type used for this step: ``"sift"`` or ``"global"`` (filters), or the
        name of the retrieval feature.
    next_feature : str
        Feature type the filter will use for the next frame.
    n_particles : int
    status : Status
    processing_ms : float
        Time spent in the core for this frame (decoding excluded).
    best_image : int
        Index of the best-matching map image this step (-1 if none).
    measurement : str
        Kind of measurement the step weighed the estimate by: ``"sift"`` or ``"global"``
        (an image similarity under that feature type), ``"registered"`` (a camera pose
        solved against the map's geometry) or ``"interpolated"`` (a match-weighted position
        between the best map images); several kinds in one step are joined by ``"+"``.
        Empty where not known.
    heading_deg, heading_sigma_deg : float or None
        Compass bearing (degrees clockwise from north) of the top edge of the frame and its
        standard deviation, where camera geometry gave one this step; None otherwise.
    metadata_used : str
        Which kinds of the frame's metadata (:data:`workers.core.metadata.METADATA_KINDS`)
        the step used, joined by ``"+"``; empty when none.
    gps_gate : str
        ``""`` when the frame carried no GPS fix, ``"used"`` when the fix was fused,
        ``"rejected"`` when it was ignored for disagreeing with the visual estimate (a
        jumping or spoofed fix).
    """

    x: float
    y: float
    lat: float
    lon: float
    sigma_x: float
    sigma_y: float
    cov: tuple[float, float, float, float]
    feature: str
    next_feature: str
    n_particles: int
    status: Status
    processing_ms: float
    best_image: int = -1
    measurement: str = ""
    heading_deg: float | None = None
    heading_sigma_deg: float | None = None
    metadata_used: str = ""
    gps_gate: str = ""
    cloud: tuple[tuple[float, float], ...] = ()
    navigation: dict | None = None
