"""Sessions that follow their map: moved to each new revision of it, between two frames.

A build that packs a new revision, or a restore, tells this process at once
(:meth:`MapFollowing.map_revised`); the revisions another API process made are read every
few seconds (:meth:`MapFollowing.follow_maps`). A session behind its map moves before its next
frame is accepted, or at once when it is idle. The move runs as a control on the session's
localiser, after every frame accepted before it, and the engine's worker carries the
filter's state across (:meth:`workers.core.localisers.base.Localiser.set_state`).
"""

from __future__ import annotations

import asyncio
import logging
import threading
import uuid
from collections.abc import Awaitable, Callable
from dataclasses import replace

from sqlalchemy import select, update

from vloc.app.maps.models import Map
from vloc.app.sessions.admission import check_revision
from vloc.app.sessions.live import LiveSession
from vloc.app.sessions.models import LocalisationSession
from vloc.app.sessions.registry import SessionRegistry

log = logging.getLogger(__name__)

Control = Callable[..., Awaitable[object]]
"""``control(live, op, **kwargs)``: run a control after the frames accepted before it."""


class MapFollowing:
    """Moving the sessions of one API process that follow their map.

    Parameters
    ----------
    sessions : SessionRegistry
        The sessions, with the settings, database and metrics they work with.
    control : callable
        Runs the ``move`` control in order with the session's frames
        (:meth:`app.sessions.intake.FrameIntake.control`).
    """

    def __init__(self, sessions: SessionRegistry, *, control: Control) -> None:
        self.sessions = sessions
        self.settings, self.db_sessions = sessions.settings, sessions.db_sessions
        self.metrics = sessions.metrics
        self.control = control
        self.loop: asyncio.AbstractEventLoop | None = None
        self._lock = threading.Lock()
        self._current: dict[str, int] = {}
        """The current revision of the maps of live sessions that follow their map, as
        this process last heard (:meth:`map_revised`, :meth:`follow_maps`)."""

    def map_revised(self, map_id: str, revision: int) -> None:
        """The map's current revision changed (built, or restored) in this process: its
        sessions that follow it move before their next frame (:meth:`follow`). Callable
        from any thread."""
        with self._lock:
            self._current[str(map_id)] = int(revision)
        if self.loop is not None and not self.loop.is_closed():
            self.loop.call_soon_threadsafe(self._spawn_moves, str(map_id))

    def _spawn_moves(self, map_id: str) -> None:
        """Event loop: move the idle following sessions of the map now (the busy ones
        move at their next frame, or here once a frame has gone)."""
        for live in self.sessions.held():
            if live.spec.map_id == map_id and self.behind(live) is not None:
                task = self.loop.create_task(self.follow(live), name=f"follow-{live.id}")
                task.add_done_callback(_log_failure)

    async def follow_maps(self) -> int:
        """Read the current revision of the maps that live sessions follow (another API
        process may have built or restored them) and move those sessions; how many
        moved."""
        maps = {live.spec.map_id for live in self.sessions.held() if live.follows_map}
        if not maps:
            return 0
        current = await asyncio.to_thread(self._read_revisions, maps)
        with self._lock:
            self._current.update(current)
        moved = 0
        for live in self.sessions.held():
            if self.behind(live) is not None:
                moved += await self.follow(live)
        return moved

    def _read_revisions(self, maps: set[str]) -> dict[str, int]:
        with self.db_sessions() as db:
            rows = db.execute(select(Map.id, Map.revision).where(
                Map.id.in_([uuid.UUID(m) for m in maps]))).all()
        return {str(i): int(r) for i, r in rows if r}

    def behind(self, live: LiveSession) -> int | None:
        """The revision a following session should move to, or None."""
        if not live.follows_map:
            return None
        current = self._current.get(live.spec.map_id)
        if current is None or current in (live.spec.revision, live.refused_revision):
            return None
        return current

    async def follow(self, live: LiveSession) -> bool:
        """Move a session that follows its map to the map's current revision, between two
        frames: every frame accepted before runs on the old revision, every frame after
        on the new one. Whether it moved; a revision it cannot move to (its files gone, a
        localiser that cannot move) is logged and not tried again, and the session goes on
        where it is."""
        while live.moving is not None:
            await asyncio.shield(live.moving)
        revision = self.behind(live)
        if revision is None:
            return False
        live.moving = self.loop.create_future()
        try:
            return await self._move(live, revision)
        finally:
            live.moving.set_result(None)
            live.moving = None

    async def _move(self, live: LiveSession, revision: int) -> bool:
        spec = replace(live.spec, revision=revision, map_folder=str(
            self.settings.packed_map_dir(live.spec.map_id, revision)))
        try:
            check_revision(spec)
            await self.control(live, "move", spec=spec)
        except Exception as exc:  # noqa: BLE001 - the session stays where it is
            live.refused_revision = revision
            self.metrics.session_moves.labels("failed").inc()
            log.warning("session %s stays on map revision %d: moving to %d failed (%s)",
                        live.id, live.spec.revision, revision, exc)
            return False
        previous, live.spec = live.spec.revision, spec
        self.metrics.session_moves.labels("moved").inc()
        await asyncio.to_thread(self._write_revision, uuid.UUID(live.id), revision)
        log.info("session %s moved from map revision %d to %d", live.id, previous, revision)
        return True

    def _write_revision(self, session_id: uuid.UUID, revision: int) -> None:
        with self.db_sessions() as db:
            db.execute(update(LocalisationSession)
                       .where(LocalisationSession.id == session_id)
                       .values(map_revision=revision))
            db.commit()


def _log_failure(task: asyncio.Task) -> None:
    if not task.cancelled() and task.exception() is not None:
        log.error("moving a session to its map's new revision failed",
                  exc_info=task.exception())
