"""What a session and a frame must satisfy to be let in: the session's spec and its
map revision on disk, and the frame's sequence number (never reused, never past the last)."""

from __future__ import annotations

from pathlib import Path

from vloc.app.config import Settings
from vloc.app.engine import DEFAULT_FACTORY, SessionSpec
from vloc.app.problems import Problem, ProblemKind
from vloc.app.sessions.models import LocalisationSession
from vloc.app.sessions.schemas import MAX_SEQ


def spec_for(row: LocalisationSession, settings: Settings) -> SessionSpec:
    folder = settings.packed_map_dir(str(row.map_id), row.map_revision)
    params, factory = dict(row.params), DEFAULT_FACTORY
    if row.navigation is not None:
        from vloc.workers.core.navigation.session import FACTORY

        # the worker builds a localiser that also follows the session's route
        params["navigation"], factory = row.navigation, FACTORY
    return SessionSpec(session_id=str(row.id), map_id=str(row.map_id),
                       revision=row.map_revision, map_folder=str(folder), mode=row.mode,
                       params=params, seed=int(row.seed), factory=factory)


def next_seq(last_seq: int | None, seq: int | None) -> int:
    """The frame's sequence number: ``seq`` when it is after ``last_seq``, else the next one.

    Raises
    ------
    Problem
        409 for a duplicate or stale ``seq``, or when the session has used the last one.
    """
    if seq is None:
        if last_seq is None:
            return 0
        if last_seq >= MAX_SEQ:
            raise Problem(409, f"the session has used every seq up to {MAX_SEQ}",
                          kind=ProblemKind.SEQ_EXHAUSTED, last_seq=last_seq)
        return last_seq + 1
    if last_seq is not None and seq <= last_seq:
        kind = ProblemKind.DUPLICATE_SEQ if seq == last_seq else ProblemKind.STALE_SEQ
        raise Problem(409, f"seq {seq} is not after the last accepted seq {last_seq}",
                      kind=kind, last_seq=last_seq)
    return seq


def check_revision(spec: SessionSpec) -> None:
    """503 ``map-revision-missing`` (naming the map, not the data path) when the packed
    revision a session needs is gone from the data directory."""
    if not Path(spec.map_folder).is_dir():
        raise revision_missing(spec.map_id, spec.revision)


def revision_missing(map_id: str, revision: int) -> Problem:
    return Problem(503, f"the files of map {map_id} revision {revision} are missing from "
                   "the data directory; restore them or rebuild the map",
                   kind=ProblemKind.MAP_REVISION_MISSING)
