"""Server-wide bounds on the frames an API process holds in memory, shared fairly between
sessions.

A frame's bytes are held from the moment its body starts to arrive until its outcome comes
back: the body as it is read, the accepted frame until the engine takes it, the engine's
own queue until a worker reads it. :class:`FrameBudget` counts the bodies being read; the
intake counts the frames accepted and not answered. A frame is let in only when both
bounds (``VLOC_MAX_QUEUED_BYTES``, ``VLOC_MAX_QUEUED_FRAMES``) hold after it:

- over a bound: 503 ``server-busy`` with ``Retry-After``, whoever sends it;
- over its fair share (the bound divided between the sessions holding frames), once the
  server is half full: 429 ``over-fair-share`` with ``Retry-After``, so that one device
  sending fast cannot take the room of the others.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass

from vloc.app.problems import Problem, ProblemKind

RETRY_AFTER_S = 1


@dataclass(frozen=True, slots=True)
class Held:
    """What the frames of one session, or of the whole process, hold."""

    frames: int = 0
    bytes: int = 0


class FrameBudget:
    """Bodies being read, and the admission rule over them and the accepted frames.

    Parameters
    ----------
    max_bytes, max_frames : int
        The server-wide bounds.
    accepted : callable
        ``() -> dict[session id, Held]``: the frames accepted and not answered yet.
    """

    def __init__(self, *, max_bytes: int, max_frames: int,
                 accepted: Callable[[], dict[str, Held]]) -> None:
        self.max_bytes = max_bytes
        self.max_frames = max_frames
        self._accepted = accepted
        self._reading_bytes: Counter[str] = Counter()
        self._reading_frames: Counter[str] = Counter()

    def held(self) -> dict[str, Held]:
        """Every session's frames, accepted or being read."""
        out = dict(self._accepted())
        for sid, n in self._reading_frames.items():
            h = out.get(sid, Held())
            out[sid] = Held(h.frames + n, h.bytes + self._reading_bytes[sid])
        return out

    def check(self, session_id: str, size: int) -> None:
        """Raise the 503 or 429 :class:`Problem` when a frame of ``size`` bytes of the
        session would not fit."""
        held = self.held()
        total = Held(sum(h.frames for h in held.values()), sum(h.bytes for h in held.values()))
        if total.frames + 1 > self.max_frames or total.bytes + size > self.max_bytes:
            raise Problem(503, f"the server holds {total.frames} frames ({total.bytes} bytes) "
                          "not answered yet, as many as it takes; send the frame again later",
                          kind=ProblemKind.SERVER_BUSY, headers={"Retry-After": str(RETRY_AFTER_S)},
                          max_queued_frames=self.max_frames, max_queued_bytes=self.max_bytes)
        mine = held.get(session_id, Held())
        sessions = len(held) + (session_id not in held)
        share = Held(self.max_frames // sessions, self.max_bytes // sessions)
        half_full = (2 * (total.frames + 1) > self.max_frames
                     or 2 * (total.bytes + size) > self.max_bytes)
        if half_full and (mine.frames + 1 > share.frames or mine.bytes + size > share.bytes):
            raise Problem(429, f"this session holds {mine.frames} frames ({mine.bytes} bytes) "
                          f"not answered yet, its share of the server's room while "
                          f"{sessions} sessions send frames; send the next one later",
                          kind=ProblemKind.OVER_FAIR_SHARE,
                          headers={"Retry-After": str(RETRY_AFTER_S)})

    @contextmanager
    def reading(self, session_id: str, size: int) -> Iterator[None]:
        """Admit a body of up to ``size`` bytes (:meth:`check`) and count it while it is
        read and accepted."""
        self.check(session_id, size)
        self._reading_bytes[session_id] += size
        self._reading_frames[session_id] += 1
        try:
            yield
        finally:
            self._reading_bytes[session_id] -= size
            self._reading_frames[session_id] -= 1
            if not self._reading_frames[session_id]:
                del self._reading_frames[session_id], self._reading_bytes[session_id]
