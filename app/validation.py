"""Plausibility of positions and times at the edge, so that nothing out of range reaches a
build, a filter or the database."""

from __future__ import annotations

import math
from datetime import UTC, datetime, timedelta

from vloc.app.problems import Problem, ProblemKind
from vloc.workers.core.metadata import FrameMetadata

MIN_ALT_M, MAX_ALT_M = -500.0, 10_000.0
"""Altitudes a camera on or above the ground can have (the Dead Sea shore to high flight)."""
EARLIEST = datetime(1990, 1, 1, tzinfo=UTC)
"""Before consumer GPS; an earlier capture time is a camera clock that was never set."""
FUTURE_SLACK = timedelta(days=1)
"""Capture times may run ahead of the server's clock by this much (time zones, drift)."""


def check_position(lat: float, lon: float, alt: float | None) -> None:
    """422 ``bad-position`` for NaN, infinite or out-of-range coordinates or altitude."""
    from vloc.workers.core.geo import check_lat_lon

    try:
        check_lat_lon(lat, lon)
    except ValueError as exc:
        raise Problem(422, str(exc), kind=ProblemKind.BAD_POSITION) from None
    if alt is not None and not (math.isfinite(alt) and MIN_ALT_M <= alt <= MAX_ALT_M):
        raise Problem(422, f"alt must be a finite number of metres in [{MIN_ALT_M:g}, "
                      f"{MAX_ALT_M:g}], got {alt!r}", kind=ProblemKind.BAD_POSITION)


def aware(t: datetime | None) -> datetime | None:
    """A time without an offset is taken as UTC."""
    return t.replace(tzinfo=UTC) if t is not None and t.tzinfo is None else t


def plausible_time(t: datetime) -> bool:
    return EARLIEST <= aware(t) <= datetime.now(UTC) + FUTURE_SLACK


def check_captured_at(t: datetime | None) -> datetime | None:
    """The capture time as an aware datetime; 422 ``bad-captured-at`` outside 1990 to
    tomorrow."""
    t = aware(t)
    if t is not None and not plausible_time(t):
        raise Problem(422, f"captured_at must lie between {EARLIEST:%Y-%m-%d} and one day "
                      f"from now, got {t.isoformat()}", kind=ProblemKind.BAD_CAPTURED_AT)
    return t


def check_metadata(values: dict) -> FrameMetadata | None:
    """A frame's metadata (:class:`workers.core.metadata.FrameMetadata` fields, None where
    absent), validated once, by the core's own checks: the FrameMetadata, which goes on to
    the localiser as it is, or None when no field is given.

    Raises Problem 422 ``bad-metadata`` naming the field (``field``) for a non-finite or
    out-of-range value or a half of a pair (``gps_lat`` without ``gps_lon``...).
    """
    given = {k: v for k, v in values.items() if v is not None}
    if not given:
        return None
    try:
        metadata = FrameMetadata(**given)
    except TypeError as exc:
        raise Problem(422, f"unknown metadata field: {exc}", kind=ProblemKind.BAD_METADATA) from None
    except ValueError as exc:
        # The core's messages start with the offending field's name.
        name = str(exc).split()[0]
        raise Problem(422, str(exc), kind=ProblemKind.BAD_METADATA,
                      field=name if name in values else None) from None
    return metadata


def check_text(value: str, field: str) -> str:
    """``value`` when it is free of NUL characters; 422 ``bad-text`` naming the field.

    PostgreSQL cannot store NUL in text, and no name or file name needs one.
    """
    if "\x00" in value:
        raise Problem(422, f"{field} contains a NUL character", kind=ProblemKind.BAD_TEXT, field=field)
    return value
