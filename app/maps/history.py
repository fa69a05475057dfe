"""A map's revisions as a person manages them: list what each holds and what changed, restore
the map to an earlier one, drop those no longer wanted (and their disk).

Every build packs a new revision beside the others (:mod:`vloc.app.jobs.service`) and records
it in ``map_revisions``. Restoring makes an earlier revision the current one again: new
sessions and single-image localisations use it, open sessions that follow the map move to it
before their next frame (those that pinned a revision keep theirs), and images added since
wait for the next build (which packs a revision after
every one the map has had, never over one). A revision is dropped only when it is not the
current one and no active session localises against it; its files go, its record stays
(marked dropped), so that its number is never used again.
"""

from __future__ import annotations

import shutil
import stat
from pathlib import Path

import numpy as np
from sqlalchemy import bindparam, func, or_, select, update
from sqlalchemy.orm import Session

from vloc.app.config import Settings
from vloc.app.db import utcnow
from vloc.app.maps.models import Map, MapImage, MapRevision, MapStatus, MapVocabulary
from vloc.app.maps.revisions import revision_images, vocabularies_from
from vloc.app.maps.schemas import RevisionRead
from vloc.app.maps.service import refuse_while_building
from vloc.app.problems import Problem, ProblemKind, not_found
from vloc.app.sessions.admission import revision_missing
from vloc.app.sessions.models import LocalisationSession
from vloc.app.sessions.store import ACTIVE
from vloc.workers.core.geo import GeoOrigin


def list_revisions(db: Session, *, map_: Map, settings: Settings) -> list[RevisionRead]:
    """The map's recorded revisions, newest first, dropped ones included."""
    active = dict(db.execute(
        select(LocalisationSession.map_revision, func.count(LocalisationSession.id))
        .where(LocalisationSession.map_id == map_.id, LocalisationSession.status == ACTIVE)
        .group_by(LocalisationSession.map_revision)).all())
    rows = db.scalars(select(MapRevision).where(MapRevision.map_id == map_.id)
                      .order_by(MapRevision.revision.desc()))
    return [_read(row, current=row.revision == map_.revision,
                  active_sessions=active.get(row.revision, 0),
                  folder=settings.packed_map_dir(str(map_.id), row.revision)) for row in rows]


def restore_revision(db: Session, *, map_: Map, revision: int, settings: Settings) -> Map:
    """Make ``revision`` the map's current revision again.

    The map takes back its frame and geometry report; its images take back their positions
    in that frame, and those the revision does not hold count as waiting for a build.
    Refused while a build runs (409 ``map-busy``); 404 for a revision not recorded or
    dropped, 503 ``map-revision-missing`` where its files are gone otherwise.
    """
    row = _revision(db, map_, revision)
    if row.dropped_at is not None:
        raise Problem(404, f"revision {revision} was dropped with its files",
                      kind=ProblemKind.NOT_FOUND)
    refuse_while_building(db, map_)
    folder = settings.packed_map_dir(str(map_.id), revision)
    held = revision_images(str(folder))
    if not held.names:
        raise revision_missing(str(map_.id), revision)
    if held.ids is None:
        raise Problem(409, f"revision {revision} was packed before revisions recorded their "
                           "images and cannot be restored; build the map again instead",
                      kind=ProblemKind.REVISION_NOT_RESTORABLE, revision=revision)
    origin = GeoOrigin(row.origin_lat, row.origin_lon, row.origin_alt or 0.0)
    ids = list(held.ids)
    images = {i: (lat, lon) for i, lat, lon in db.execute(
        select(MapImage.id, MapImage.lat, MapImage.lon).where(MapImage.map_id == map_.id))}
    kept = [i for i in ids if i in images]
    table = MapImage.__table__
    db.execute(update(table).where(table.c.map_id == map_.id, table.c.id.not_in(kept))
               .values(built_revision=None, east=None, north=None))
    if kept:
        db.execute(update(table).where(
            table.c.id.in_(kept),
            or_(table.c.built_revision.is_(None), table.c.built_revision > revision))
            .values(built_revision=revision))
        east, north = origin.to_local([images[i][0] for i in kept],
                                      [images[i][1] for i in kept])
        db.execute(update(table).where(table.c.id == bindparam("image_id"))
                   .values(east=bindparam("image_east"), north=bindparam("image_north")),
                   [{"image_id": i, "image_east": float(e), "image_north": float(n)}
                    for i, e, n in zip(kept, np.atleast_1d(east), np.atleast_1d(north),
                                       strict=True)])
    map_.revision = revision
    map_.origin_lat, map_.origin_lon, map_.origin_alt = (row.origin_lat, row.origin_lon,
                                                         row.origin_alt)
    map_.built_at, map_.geometry = row.built_at, row.geometry
    map_.status = MapStatus.READY if len(kept) == len(images) else MapStatus.UNBUILT
    db.commit()
    return map_


def drop_revision(db: Session, *, map_: Map, revision: int, settings: Settings) -> None:
    """Delete a revision's vocabularies and files and mark its record dropped; a revision
    dropped already stays so.

    Refused for the current revision (409 ``revision-current``: restore another first) and
    for one that active sessions localise against (409 ``revision-in-use``)."""
    row = _revision(db, map_, revision)
    if row.dropped_at is not None:
        return
    if revision == map_.revision:
        raise Problem(409, f"revision {revision} is the map's current revision; restore "
                           "another one before dropping it", kind=ProblemKind.REVISION_CURRENT,
                      revision=revision)
    refuse_while_building(db, map_)
    sessions = db.scalar(select(func.count(LocalisationSession.id)).where(
        LocalisationSession.map_id == map_.id, LocalisationSession.map_revision == revision,
        LocalisationSession.status == ACTIVE))
    if sessions:
        raise Problem(409, f"{sessions} active session(s) localise against revision "
                           f"{revision}; delete them or let them expire first",
                      kind=ProblemKind.REVISION_IN_USE, revision=revision, sessions=sessions)
    row.dropped_at = utcnow()
    db.execute(MapVocabulary.__table__.delete().where(
        MapVocabulary.map_id == map_.id, MapVocabulary.revision == revision))
    db.commit()
    shutil.rmtree(settings.packed_map_dir(str(map_.id), revision), ignore_errors=True)


def _revision(db: Session, map_: Map, revision: int) -> MapRevision:
    row = db.get(MapRevision, (map_.id, revision))
    if row is None:
        raise not_found("revision", revision)
    return row


def _read(row: MapRevision, *, current: bool, active_sessions: int,
          folder: Path) -> RevisionRead:
    present = row.dropped_at is None and folder.is_dir()
    size, shared = _disk(folder) if present else (None, None)
    return RevisionRead(
        revision=row.revision, current=current, built_at=row.built_at, job_id=row.job_id,
        base_revision=row.base_revision, image_count=row.image_count, added=row.added,
        removed=row.removed, active_sessions=active_sessions, disk_bytes=size,
        shared_bytes=shared,
        vocabularies_from=vocabularies_from(str(folder)) if present else None,
        dropped_at=row.dropped_at, geometry=row.geometry)


def _disk(folder: Path) -> tuple[int, int]:
    """Bytes of a revision's files, and of those it shares with other revisions (files
    hard-linked into several revision folders: :mod:`vloc.workers.core.rowchunks`)."""
    size = shared = 0
    for path in folder.rglob("*"):
        st = path.lstat()
        if stat.S_ISREG(st.st_mode):
            size += st.st_size
            shared += st.st_size if st.st_nlink > 1 else 0
    return size, shared
