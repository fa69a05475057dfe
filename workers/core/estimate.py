"""What a localiser returns for each frame, and what a client is told of it."""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

from .accuracy import horizontal_accuracy


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


@dataclass(frozen=True, slots=True)
class Verdict:
    """What a client is told of an estimate (:func:`judge`)."""

    status: Status
    converged: bool
    horizontal_accuracy_m: float


def judge(status: Status, cov, *, bound_m: float, converged_before: bool) -> Verdict:
    """An estimate's status, ``converged`` flag and horizontal accuracy, as told to a
    client, from the localiser's ``status`` and the position covariance ``cov`` (4
    floats, row-major): the one place they are decided.

    The accuracy is the 68 % circle of the covariance
    (:func:`~workers.core.accuracy.horizontal_accuracy`). Converged: the localiser tracks
    and the accuracy is within ``bound_m``. Until the first converged estimate (of the
    session, or since a reset or an initial pose: ``converged_before``), a tracking
    estimate is still ``initialising``; after it, one that is not converged is
    ``tracking`` as the localiser says, or ``lost``.
    """
    accuracy = float(horizontal_accuracy(cov))
    status = Status(status)
    converged = status is Status.TRACKING and accuracy <= bound_m
    if status is Status.TRACKING and not converged and not converged_before:
        status = Status.INITIALISING
    return Verdict(status, converged, accuracy)
