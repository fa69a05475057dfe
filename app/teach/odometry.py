"""The odometry CSV of a taught route: parsed and checked before anything is stored.

Columns (header required, any order, extra columns refused): ``filename, x, y, theta`` and
optionally ``lat, lon``. One row per image, in driving order; ``x, y`` in metres and
``theta`` in radians counter-clockwise from the odometry's x axis, as the robot's wheel
odometry integrates them; ``lat, lon`` a GPS fix of the image, where there was one (both
or neither, empty cells allowed).
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass

from vloc.app.problems import Problem, ProblemKind

REQUIRED = ("filename", "x", "y", "theta")
OPTIONAL = ("lat", "lon")
MAX_ROWS = 100_000
MAX_COORD = 1e7


@dataclass(frozen=True, slots=True)
class OdometryRow:
    filename: str
    x: float
    y: float
    theta: float
    lat: float | None
    lon: float | None


def _bad(detail: str, *, row: int | None = None, column: str | None = None) -> Problem:
    loc = ["body", "odometry"] + ([row] if row is not None else []) + \
        ([column] if column is not None else [])
    where = f"odometry row {row}" if row is not None else "odometry"
    return Problem(422, f"{where}: {detail}", kind=ProblemKind.BAD_ODOMETRY,
                   errors=[{"loc": loc, "msg": detail, "type": ProblemKind.BAD_ODOMETRY}])


def parse_odometry(data: bytes, *, max_step_m: float) -> list[OdometryRow]:
    """The rows of an odometry CSV, or a 422 problem naming the first bad row and column.

    Rows are numbered from 1 after the header. Refused: a missing or unknown column, fewer
    than three rows, an empty filename or one given twice, a value that is not a finite
    number (NaN, inf, text) or is out of range, ``lat`` without ``lon``, and a gap: two
    consecutive rows further apart than ``max_step_m`` (images missing from the sequence).
    """
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError:
        raise _bad("is not UTF-8 text") from None
    reader = csv.DictReader(io.StringIO(text, newline=""))
    header = [h.strip() for h in (reader.fieldnames or [])]
    missing = [c for c in REQUIRED if c not in header]
    if missing:
        raise _bad(f"missing column(s) {', '.join(missing)}; the header must name "
                   f"{', '.join(REQUIRED)} (and optionally lat, lon)")
    unknown = [c for c in header if c not in REQUIRED + OPTIONAL]
    if unknown:
        raise _bad(f"unknown column(s) {', '.join(unknown)}")
    if len(set(header)) != len(header):
        raise _bad("a column is named twice")
    reader.fieldnames = header
    rows: list[OdometryRow] = []
    seen: dict[str, int] = {}
    for n, raw in enumerate(reader, start=1):
        if n > MAX_ROWS:
            raise _bad(f"more than {MAX_ROWS} rows")
        if None in raw or any(v is None for v in raw.values()):
            raise _bad("has a different number of cells than the header", row=n)
        name = raw["filename"].strip()
        if not name:
            raise _bad("empty filename", row=n, column="filename")
        if "\x00" in name:
            raise _bad("the filename contains a NUL character", row=n, column="filename")
        if name in seen:
            raise _bad(f"{name} is already row {seen[name]}", row=n, column="filename")
        seen[name] = n
        x, y, theta = (_number(raw[c], n, c, MAX_COORD) for c in ("x", "y", "theta"))
        lat = _optional(raw.get("lat"), n, "lat", 90.0)
        lon = _optional(raw.get("lon"), n, "lon", 180.0)
        if (lat is None) != (lon is None):
            raise _bad("give both lat and lon, or neither", row=n,
                       column="lat" if lat is None else "lon")
        if rows:
            step = math.hypot(x - rows[-1].x, y - rows[-1].y)
            if step > max_step_m:
                raise _bad(f"a gap of {step:.2f} m after row {n - 1} (at most {max_step_m:g} m "
                           "between consecutive images); are images missing from the sequence?",
                           row=n)
        rows.append(OdometryRow(name, x, y, theta, lat, lon))
    if len(rows) < 3:
        raise _bad(f"{len(rows)} row(s); a route needs at least 3 images")
    return rows


def _number(cell: str, row: int, column: str, bound: float) -> float:
    try:
        value = float(cell)
    except ValueError:
        raise _bad(f"{column} {cell.strip()!r} is not a number", row=row, column=column) from None
    if not math.isfinite(value):
        raise _bad(f"{column} is {cell.strip()}, not a finite number", row=row, column=column)
    if abs(value) > bound:
        raise _bad(f"{column} {value:g} is outside [-{bound:g}, {bound:g}]", row=row,
                   column=column)
    return value


def _optional(cell: str | None, row: int, column: str, bound: float) -> float | None:
    if cell is None or not cell.strip():
        return None
    return _number(cell, row, column, bound)
