"""The pose record, mapped once.

:class:`~app.sessions.schemas.PoseEstimate` declares a pose's fields. Everything else is
derived from it here:

- the columns of ``pose_estimates`` (:func:`pose_columns`), from each field's type;
- a pose message and its row from a worker's estimate (:func:`from_estimate`): fields of
  the core's :class:`~workers.core.estimate.Estimate` are copied by name;
- a row's values from a pose (:func:`to_row`) and a pose from a row (:func:`from_row`).

So a field is added to the schema (and to the migration that adds its column), and nowhere
else. An object or list field (other than ``cov``) is stream-only: it has no column, and
must have a default so that a stored pose reads back without it. ``cov`` is stored as four
columns; the map is the session's, and the revision has a column of the table's own (a
session following its map moves between revisions); ``geopose`` is computed from the other
fields.
"""

from __future__ import annotations

import enum
import types
import typing
import uuid
from dataclasses import dataclass
from datetime import datetime

from pydantic.fields import FieldInfo
from sqlalchemy import JSON, BigInteger, Boolean, Column, Float, Integer, String, Text
from sqlalchemy.types import TypeEngine

from vloc.app.db import UTCDateTime
from vloc.app.maps.revisions import revision_images
from vloc.app.sessions.schemas import NavigationState, PoseEstimate, PoseFields
from vloc.workers.core.estimate import Estimate, judge
from vloc.workers.core.metadata import DEFAULT_HEADING_ACCURACY_DEG, FrameMetadata

NOT_STORED = ("type", "session_id", "seq", "map_id", "map_revision")
"""Fields that are no generated column: the key, the session's map, and the revision (a
column of the table's own, :class:`~app.sessions.models.Pose`)."""
COV_COLUMNS = ("cov_xx", "cov_xy", "cov_yx", "cov_yy")
JSON_FIELDS = ("navigation",)
"""Object fields that are stored whole, as one JSON column."""
WIDE_INTS = ("image_id",)
"""Integer fields that hold another table's 64-bit id."""


def stored_fields() -> tuple[str, ...]:
    """The fields with a column: every one but the key, the session's map and the
    stream-only ones (objects and lists other than ``cov``, such as a sample of the
    particle cloud: they go out on the stream and are not kept)."""
    return tuple(n for n, info in PoseEstimate.model_fields.items()
                 if n not in NOT_STORED
                 and (n == "cov" or n in JSON_FIELDS or _scalar(info.annotation)))


def _scalar(annotation) -> bool:
    base, _ = _unwrap_any(annotation)
    return base in (bool, int, float, str, datetime) or \
        typing.get_origin(base) is typing.Literal or \
        (isinstance(base, type) and issubclass(base, enum.Enum))


def _unwrap_any(annotation) -> tuple[object, bool]:
    """As :func:`_unwrap`, but a union of several types is returned whole."""
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(annotation) if a is not type(None)]
        return (args[0] if len(args) == 1 else annotation), True
    return annotation, False


# -- the table ---------------------------------------------------------------------------------

def pose_columns() -> list[Column]:
    """The columns of ``pose_estimates`` that hold a pose's fields."""
    columns = []
    for name in stored_fields():
        info = PoseEstimate.model_fields[name]
        if name == "cov":
            columns += [Column(c, Float(), nullable=False) for c in COV_COLUMNS]
            continue
        if name in JSON_FIELDS:
            columns.append(Column(name, JSON(), nullable=True))
            continue
        sql, nullable = _sql_type(name, info)
        columns.append(Column(name, sql, nullable=nullable))
    return columns


def _sql_type(name: str, info: FieldInfo) -> tuple[TypeEngine, bool]:
    base, nullable = _unwrap(info.annotation)
    if base is bool:
        return Boolean(), nullable
    if base is int:
        wide = BigInteger().with_variant(Integer(), "sqlite")
        return (wide if name in WIDE_INTS else Integer()), nullable
    if base is float:
        return Float(), nullable
    if base is datetime:
        return UTCDateTime(), nullable
    if typing.get_origin(base) is typing.Literal or (
            isinstance(base, type) and issubclass(base, enum.Enum)):
        return String(16), nullable
    if base is str:
        limit = next((m.max_length for m in info.metadata
                      if getattr(m, "max_length", None) is not None), None)
        return (String(limit) if limit else Text()), nullable
    raise TypeError(f"PoseEstimate.{name}: no column type for {info.annotation!r}")


def _unwrap(annotation) -> tuple[object, bool]:
    """``X | None`` -> (X, True); ``X`` -> (X, False)."""
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(annotation) if a is not type(None)]
        if len(args) != 1:
            raise TypeError(f"no column type for {annotation!r}")
        return args[0], True
    return annotation, False


# -- rows --------------------------------------------------------------------------------------

def to_row(pose: PoseEstimate) -> dict:
    """The values of a pose's row in ``pose_estimates``: its stored fields and the
    revision."""
    row = {"map_revision": pose.map_revision}
    for name in stored_fields():
        value = getattr(pose, name)
        if name == "cov":
            row.update(zip(COV_COLUMNS, value, strict=True))
            continue
        if name in JSON_FIELDS and value is not None:
            value = value.model_dump(mode="json")
        row[name] = value
    return row


def from_row(row, *, map_id: uuid.UUID, map_revision: int) -> PoseEstimate:
    """A stored pose (a :class:`~app.sessions.models.Pose`) as its schema; ``map_revision``
    (the session's) where the row names none."""
    values = {n: getattr(row, n) for n in stored_fields() if n != "cov"}
    return PoseEstimate(session_id=row.session_id, seq=row.seq, map_id=map_id,
                        map_revision=row.map_revision if row.map_revision is not None
                        else map_revision,
                        cov=[getattr(row, c) for c in COV_COLUMNS], **values)


# -- from a worker's estimate --------------------------------------------------------------------

@dataclass(frozen=True, slots=True)
class FrameContext:
    """What the service knows of a frame beside the worker's estimate."""

    session_id: str
    seq: int
    map_id: str
    map_revision: int
    map_folder: str
    captured_at: datetime | None
    received_at: datetime
    metadata: FrameMetadata | None
    decode_ms: float
    latency_ms: float


def from_estimate(estimate: Estimate, ctx: FrameContext, *, bound_m: float,
                  converged_before: bool) -> tuple[PoseEstimate, dict]:
    """The pose message of a worker's estimate, and its row (:func:`to_row`).

    The pose is assembled, not validated: every value is the core's typed estimate or the
    service's own, each of its field's type (the tests hold it to the schema). So nothing
    on a frame's way is made twice; the message is written as JSON once, by the schema's
    serializer, and the row is read from the same object.
    """
    navigation = None
    if estimate.navigation is not None:  # the follower's figures, typed by the schema
        navigation = NavigationState.model_validate(estimate.navigation)
    fields = pose_fields(
        estimate, map_id=uuid.UUID(ctx.map_id), map_revision=ctx.map_revision,
        map_folder=ctx.map_folder, metadata=ctx.metadata, decode_ms=ctx.decode_ms,
        bound_m=bound_m, converged_before=converged_before)
    message = PoseEstimate.model_construct(
        **fields, session_id=uuid.UUID(ctx.session_id), seq=ctx.seq,
        captured_at=ctx.captured_at, received_at=ctx.received_at, latency_ms=ctx.latency_ms,
        navigation=navigation)
    return message, to_row(message)


_NO_METADATA = FrameMetadata()
"""A frame that came without sensor reports (made once, not for every such frame)."""


_SHARED = tuple(n for n in PoseFields.model_fields if n in Estimate.__dataclass_fields__)
"""The fields a pose copies from the core's estimate by name."""


def pose_fields(estimate: Estimate, *, map_id: uuid.UUID, map_revision: int, map_folder: str,
                metadata: FrameMetadata | None, decode_ms: float, bound_m: float,
                converged_before: bool) -> dict:
    """The :class:`~app.sessions.schemas.PoseFields` of an estimate, each of its field's
    type: the core's fields by name, the core's verdict on it (status, convergence,
    accuracy: :func:`~workers.core.estimate.judge`), and what the service adds (the heading
    the device reported, the matched image's id and name)."""
    shared = {k: getattr(estimate, k) for k in _SHARED}
    shared["cov"] = list(estimate.cov)
    shared["cloud"] = list(estimate.cloud)
    verdict = judge(estimate.status, estimate.cov, bound_m=bound_m,
                    converged_before=converged_before)
    meta = metadata or _NO_METADATA
    heading = (estimate.heading_deg, estimate.heading_sigma_deg, "geometry")
    if heading[0] is None:
        heading = (meta.heading_deg, meta.heading_accuracy_deg, "device") \
            if meta.heading_deg is not None else (None, None, None)
    if heading[0] is not None and heading[1] is None:
        heading = (heading[0], DEFAULT_HEADING_ACCURACY_DEG, heading[2])
    image_id, filename = revision_images(map_folder).lookup(estimate.best_image)
    return shared | {
        "map_id": map_id, "map_revision": map_revision, "status": verdict.status,
        "converged": verdict.converged, "horizontal_accuracy_m": verdict.horizontal_accuracy_m,
        "altitude_m": meta.altitude_m, "heading_deg": heading[0],
        "heading_sigma_deg": heading[1], "heading_source": heading[2], "image_id": image_id,
        "image_filename": filename, "decode_ms": decode_ms}
