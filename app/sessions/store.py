"""The frame intake's writes: frame records, frame outcomes, and the frames a stopped
server left queued.

Isolation: a batch (frames of many sessions) is written in one transaction; when the
database refuses it, every item is written again in a transaction of its own, so a row the
database cannot take costs that row only, never another session's rows of the batch.

Durability: a commit survives a crash of the API process. On PostgreSQL the writer does not
wait for the database's disk (``synchronous_commit`` off for its transactions), which is
what SQLite gives in WAL mode with ``synchronous=NORMAL``: the last commits before a power
loss of the database host may be lost, nothing else.
"""

from __future__ import annotations

import logging
import uuid
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime

from sqlalchemy import bindparam, func, insert, select, text, update
from sqlalchemy.orm import Session, sessionmaker

from vloc.app.db import utcnow
from vloc.app.engine import Checkpoint, FrameFailed, Outcome
from vloc.app.sessions.models import Frame, FrameStatus, LocalisationSession, Pose
from vloc.app.stream.hub import Encoded

log = logging.getLogger(__name__)

ACTIVE, EXPIRED = "active", "expired"
"""A session's ``status``."""
INTERRUPTED_REASON = "the server stopped before answering this frame"
REASON_CHARS = 2000

_frames = Frame.__table__
_SETTLE_FRAME = (
    update(_frames)
    .where(_frames.c.session_id == bindparam("b_session"), _frames.c.seq == bindparam("b_seq"))
    .values(status=bindparam("b_status"), error_kind=bindparam("b_kind"),
            error_reason=bindparam("b_reason"), latency_ms=bindparam("b_latency")))


@dataclass(frozen=True, slots=True)
class FrameRecord:
    """An accepted frame, recorded (``queued``) before it goes to a worker."""

    session_id: str
    seq: int
    received_at: datetime
    captured_at: datetime | None


@dataclass(frozen=True, slots=True)
class OutcomeRecord:
    """A frame's outcome (or a checkpoint) with its message (None for a checkpoint) and,
    for a pose, its row in ``pose_estimates`` (:func:`app.sessions.pose.to_row`)."""

    outcome: Outcome
    message: Encoded | None
    row: dict | None = None


class FrameStore:
    """Writes for :class:`~app.sessions.intake.FrameIntake`, from its writer thread."""

    def __init__(self, db_sessions: sessionmaker[Session], *, owner: str) -> None:
        self.db_sessions = db_sessions
        self.owner = owner

    def write(self, items: Sequence[FrameRecord | OutcomeRecord]) -> dict[int, Exception]:
        """Store the items; the ones the database refused, by index, with its error."""
        if not items:
            return {}
        try:
            self._transaction(items)
            return {}
        except Exception as exc:  # noqa: BLE001 - whatever the driver refuses, isolate it
            if len(items) == 1:
                return {0: exc}
            log.warning("a batch of %d items was refused (%s: %s); storing them one by one",
                        len(items), type(exc).__name__, exc)
        refused: dict[int, Exception] = {}
        for i, item in enumerate(items):
            try:
                self._transaction([item])
            except Exception as exc:  # noqa: BLE001 - reported by the caller, row by row
                refused[i] = exc
        return refused

    def _transaction(self, items: Sequence[FrameRecord | OutcomeRecord]) -> None:
        records = [i for i in items if isinstance(i, FrameRecord)]
        by_session: dict[str, list[OutcomeRecord]] = defaultdict(list)
        for item in items:
            if isinstance(item, OutcomeRecord):
                by_session[item.outcome.session_id].append(item)
        with self.db_sessions() as db:
            if db.get_bind().dialect.name == "postgresql":
                # Durable once PostgreSQL has it, without waiting for its disk: what a crash
                # of this process needs, and what SQLite gives in WAL mode with NORMAL sync.
                db.execute(text("SET LOCAL synchronous_commit TO OFF"))
            if records:
                db.execute(insert(Frame), [
                    {"session_id": uuid.UUID(r.session_id), "seq": r.seq,
                     "received_at": r.received_at, "captured_at": r.captured_at,
                     "status": FrameStatus.QUEUED, "owner": self.owner} for r in records])
            settled = []
            # Locked (PostgreSQL), in one order: API processes sharing an engine store
            # outcomes of the same session, and the counters are read, then written.
            for session_id, outcomes in sorted(by_session.items()):
                row = db.get(LocalisationSession, uuid.UUID(session_id), with_for_update=True)
                if row is None:
                    continue  # deleted meanwhile: its frames went with it
                for item in outcomes:
                    if (frame := _apply(db, row, item)) is not None:
                        settled.append(frame)
            if settled:
                db.execute(_SETTLE_FRAME, settled)
            db.commit()


def _apply(db: Session, row: LocalisationSession, item: OutcomeRecord) -> dict | None:
    """Apply one outcome to its session; the frame's settled status (bind parameters)."""
    outcome, msg = item.outcome, item.message
    if isinstance(outcome, Checkpoint):
        if outcome.seq is None:
            row.state = outcome.state
        elif row.state_seq is None or outcome.seq >= row.state_seq:
            row.state, row.state_seq = outcome.state, outcome.seq
        return None
    row.last_seq = outcome.seq if row.last_seq is None else max(row.last_seq, outcome.seq)
    row.last_active_at = utcnow()
    frame = {"b_session": row.id, "b_seq": outcome.seq, "b_status": FrameStatus.ANSWERED,
             "b_kind": None, "b_reason": None,
             "b_latency": msg["latency_ms"] if msg is not None else None}
    if isinstance(outcome, FrameFailed):
        row.frames_failed += 1
        return frame | {"b_status": FrameStatus.FAILED, "b_kind": outcome.kind,
                        "b_reason": outcome.reason[:REASON_CHARS]}
    row.frames_processed += 1
    # Several API processes store a shared engine's outcomes: an older checkpoint stored
    # after a newer one must not replace it.
    if outcome.state is not None and (row.state_seq is None or outcome.seq >= row.state_seq):
        row.state, row.state_seq = outcome.state, outcome.seq
    if item.row is not None:
        db.add(Pose(session_id=row.id, seq=outcome.seq, **item.row))
    return frame


# -- frames a stopped server left queued ------------------------------------------------------

def interrupt_left_queued(db: Session, *, owner: str) -> int:
    """At start-up: the frames this instance recorded and did not answer before it stopped."""
    return _interrupt(db, Frame.owner == owner)


def interrupt_orphans(db: Session, *, session_id: uuid.UUID, owner: str) -> int:
    """The frames of a session that another instance left queued: a session lives in one
    process, and this one is opening it, so that instance holds it no more."""
    return _interrupt(db, (Frame.session_id == session_id) & (Frame.owner != owner))


def settle_gone(db: Session, *, alive: set[str]) -> list[Frame]:
    """The frames left queued by instances no longer alive (a shared engine's API
    processes that died): failed, kind ``interrupted``, and counted as reported, since the
    caller publishes them to the sessions' streams at once."""
    frames: list[Frame] = []
    _interrupt(db, Frame.owner.not_in(alive), status=FrameStatus.FAILED, found=frames)
    return frames


def _interrupt(db: Session, where, *, status: FrameStatus = FrameStatus.INTERRUPTED,
               found: list[Frame] | None = None) -> int:
    query = select(Frame).where(Frame.status == FrameStatus.QUEUED, where) \
        .order_by(Frame.session_id, Frame.seq)
    if db.get_bind().dialect.name == "postgresql":
        # two live processes settling the same frames would count them twice
        query = query.with_for_update(skip_locked=True)
    frames = list(db.scalars(query))
    by_session: dict[uuid.UUID, list[Frame]] = defaultdict(list)
    for frame in frames:
        frame.status, frame.error_kind = status, "interrupted"
        frame.error_reason = INTERRUPTED_REASON
        by_session[frame.session_id].append(frame)
    for session_id, lost in by_session.items():
        row = db.get(LocalisationSession, session_id)
        top = max(f.seq for f in lost)
        row.frames_failed += len(lost)
        row.last_seq = top if row.last_seq is None else max(row.last_seq, top)
    db.commit()
    if found is not None:
        found.extend(frames)
    return len(frames)


def take_interrupted(db: Session, *, session_id: uuid.UUID) -> list[Frame]:
    """The session's interrupted frames not yet reported on a stream, in order; from now on
    they count as reported (``failed``, kind ``interrupted``)."""
    frames = list(db.scalars(select(Frame).where(
        Frame.session_id == session_id, Frame.status == FrameStatus.INTERRUPTED)
        .order_by(Frame.seq)))
    for frame in frames:
        frame.status = FrameStatus.FAILED
    if frames:
        db.commit()
    return frames


def last_recorded_seq(db: Session, *, session_id: uuid.UUID) -> int | None:
    """The highest ``seq`` ever accepted for the session, answered or not."""
    return db.scalar(select(func.max(Frame.seq)).where(Frame.session_id == session_id))


def converged_since_start(db: Session, *, session_id: uuid.UUID) -> bool:
    """Whether the session's estimates had converged by its last stored pose (which is no
    longer ``initialising`` then)."""
    status = db.scalar(select(Pose.status).where(Pose.session_id == session_id)
                       .order_by(Pose.seq.desc()).limit(1))
    return status is not None and status != "initialising"


def expire(db: Session, *, session_id: uuid.UUID) -> None:
    db.execute(update(LocalisationSession).where(LocalisationSession.id == session_id)
               .values(status=EXPIRED))
    db.commit()


def keep_alive(db: Session, *, session_id: uuid.UUID) -> None:
    db.execute(update(LocalisationSession).where(LocalisationSession.id == session_id)
               .values(last_active_at=utcnow()))
    db.commit()
