"""The files the service keeps beside a packed map revision, whose folder the core writes
(:meth:`~workers.core.mapdata.MapData.save`): the database ids of its images and the time
each stage of its build took; and what the service reads of the folder's own
``meta.json``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

IMAGE_IDS_FILE = "image_ids.json"
"""Beside a packed map revision: the database id of each of its images, in map order."""
TIMINGS_FILE = "build_timings.json"
"""Beside a packed map revision: the (wall, CPU) seconds each stage of packing it took."""


@dataclass(frozen=True, slots=True)
class RevisionImages:
    """The images of one packed map revision, in map order (an estimate's ``best_image``
    indexes them)."""

    ids: tuple[int, ...] | None
    """None for a revision packed before the ids were written beside it."""
    names: tuple[str, ...]

    def lookup(self, index: int) -> tuple[int | None, str | None]:
        if not 0 <= index < len(self.names):
            return None, None
        return (self.ids[index] if self.ids is not None else None), self.names[index]


@lru_cache(maxsize=64)
def revision_images(folder: str) -> RevisionImages:
    """Read once per revision folder (a packed revision never changes)."""
    path = Path(folder)
    try:
        names = tuple(json.loads((path / "meta.json").read_text())["names"])
    except (OSError, ValueError, KeyError):
        return RevisionImages(None, ())
    try:
        ids = tuple(int(i) for i in json.loads((path / IMAGE_IDS_FILE).read_text()))
    except (OSError, ValueError):
        ids = None
    if ids is not None and len(ids) != len(names):
        ids = None
    return RevisionImages(ids, names)


def write_image_ids(folder: str | Path, image_ids: list[int]) -> None:
    """Record the database ids of a packed revision's images beside it."""
    (Path(folder) / IMAGE_IDS_FILE).write_text(json.dumps([int(i) for i in image_ids]))


def write_timings(folder: str | Path, timings: dict[str, tuple[float, float]]) -> None:
    """Record the (wall, CPU) seconds of each stage of a revision's packing beside it."""
    (Path(folder) / TIMINGS_FILE).write_text(json.dumps(
        {name: {"wall_s": wall, "cpu_s": cpu} for name, (wall, cpu) in timings.items()},
        indent=1))


@lru_cache(maxsize=64)
def vocabularies_from(folder: str) -> int | None:
    """The revision that trained a packed revision's place vocabularies (its ``meta.json``
    records it with each one's fit); None where it does not say or cannot be read."""
    try:
        meta = json.loads((Path(folder) / "meta.json").read_text())
    except (OSError, ValueError):
        return None
    found = {int(v["trained_revision"]) for v in meta.get("vocabularies", {}).values()
             if isinstance(v, dict) and "trained_revision" in v}
    return min(found) if found else None
