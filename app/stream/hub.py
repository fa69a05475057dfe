"""In-process fan-out of a session's messages to its subscribers.

Every method runs on the event loop. Each subscriber has a bounded queue: a subscriber that
stops reading is cut off (its socket closed with 1013) rather than growing without bound or
holding up the others.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections import defaultdict

SUBSCRIBER_QUEUE = 1024

CLOSED = {"type": "closed", "reason": "the session was deleted"}
OVERFLOW = {"type": "overflow"}
GOING_AWAY = {"type": "going_away"}
"""Not sent: tells a stream to close with 1001 after the messages before it."""


class Subscription:
    def __init__(self, session_id: str) -> None:
        self.session_id = session_id
        self.queue: asyncio.Queue[dict] = asyncio.Queue(SUBSCRIBER_QUEUE)
        self.overflowed = False
        self.ending = False

    def put(self, message: dict) -> None:
        if self.overflowed or self.ending:
            return
        if message is GOING_AWAY:
            self.ending = True
            self.queue.put_nowait(message)  # there is always room for the last one
            return
        if self.queue.qsize() >= SUBSCRIBER_QUEUE - 1:
            self.overflowed = True
            self.queue.put_nowait(OVERFLOW)
            return
        self.queue.put_nowait(message)

    async def get(self) -> dict:
        return await self.queue.get()


class LocalHub:
    """Subscribers of this process only (one API replica)."""

    def __init__(self) -> None:
        self._subs: dict[str, set[Subscription]] = defaultdict(set)
        self._empty = asyncio.Event()
        self._empty.set()

    async def start(self) -> None:
        pass

    async def stop(self) -> None:
        for subs in list(self._subs.values()):
            for sub in list(subs):
                sub.put(CLOSED)

    def subscribe(self, session_id: str) -> Subscription:
        sub = Subscription(session_id)
        self._subs[session_id].add(sub)
        self._empty.clear()
        return sub

    async def ready(self, session_id: str) -> None:
        """Return once messages published from now on reach this process's subscribers."""

    def unsubscribe(self, sub: Subscription) -> None:
        subs = self._subs.get(sub.session_id)
        if subs is not None:
            subs.discard(sub)
            if not subs:
                del self._subs[sub.session_id]
        if not self._subs:
            self._empty.set()

    async def going_away(self, timeout: float) -> None:
        """End every stream of this process: each sends what it was given, then closes
        with 1001. Returns once they have all ended, or after ``timeout``."""
        for subs in list(self._subs.values()):
            for sub in list(subs):
                sub.put(GOING_AWAY)
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self._empty.wait(), timeout)

    def subscriber_count(self) -> int:
        return sum(len(s) for s in self._subs.values())

    def publish(self, session_id: str, message: dict) -> None:
        """Deliver to this process's subscribers of the session."""
        self.deliver(session_id, message)

    def deliver(self, session_id: str, message: dict) -> None:
        for sub in list(self._subs.get(session_id, ())):
            sub.put(message)

    def close_session(self, session_id: str) -> None:
        self.publish(session_id, CLOSED)
