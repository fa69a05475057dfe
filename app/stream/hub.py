"""In-process fan-out of a session's messages to its subscribers.

Every method runs on the event loop. Each subscriber has a bounded queue: a subscriber that
stops reading is cut off (its socket closed with 1013) rather than growing without bound or
holding up the others.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
from collections import defaultdict

from pydantic import BaseModel

SUBSCRIBER_QUEUE = 1024

CLOSED = {"type": "closed", "kind": "session-deleted", "reason": "the session was deleted"}
EXPIRED = {"type": "closed", "kind": "session-expired",
           "reason": "the session expired after its time to live without a frame or "
                     "keep-alive; create a new session"}
"""The last message of a session's streams: ``kind`` says why they end (the close code
follows from it, see :mod:`app.stream.router`)."""
OVERFLOW = {"type": "overflow"}
GOING_AWAY = {"type": "going_away"}
"""Not sent: tells a stream to close with 1001 after the messages before it."""


HEAD = ("type", "seq", "prev_seq", "kind", "reason", "captured_at", "feature", "processing_ms",
        "latency_ms")
"""The fields of a frame's message the service reads itself (routing, ordering, metrics,
the HTTP answer's status): kept beside its JSON text, so that it is never parsed back."""


class Encoded(dict):
    """A message written as JSON once: every socket, Redis and a waiting request send its
    ``text`` as it is. As a dict it holds only the fields read here (:data:`HEAD`), so
    that the hub reads it as it reads its other messages, plain dicts."""

    __slots__ = ("text",)

    @classmethod
    def of(cls, model: BaseModel) -> Encoded:
        """A frame's message (a pose or a frame error), encoded by its schema."""
        message = cls({k: getattr(model, k) for k in HEAD if hasattr(model, k)})
        message.text = model.model_dump_json()
        return message

    @classmethod
    def received(cls, text: str) -> Encoded:
        """A message another replica encoded (through Redis): read, not written again."""
        message = cls(json.loads(text))
        message.text = text
        return message

    def after(self, prev_seq: int) -> Encoded:
        """The message with ``prev_seq`` (see :class:`Subscription`) added to its text."""
        message = Encoded(self, prev_seq=prev_seq)
        message.text = f'{self.text[:-1]},"prev_seq":{int(prev_seq)}}}'
        return message

    def fields(self) -> dict:
        """Every field, read from the text (for another form of the message, such as a
        GeoJSON feature)."""
        return json.loads(self.text)


REORDER_WAIT_S = 1.0
"""How long a frame's message waits for the one its ``prev_seq`` names before it is passed
on anyway (that one may never come: its replica died)."""


class Subscription:
    """One stream's queue of a session's messages.

    A frame's message carries ``prev_seq``, the frame its worker answered just before it.
    Messages published by different replicas can reach this one out of that order; one whose
    predecessor has not been passed on waits for it (up to :data:`REORDER_WAIT_S`), so that a
    stream sees the frames in the order they were stepped.

    ``after_seq`` is the session's last accepted seq when the stream began: a predecessor
    numbered up to it may have been published before, so nothing waits for it.
    """

    def __init__(self, session_id: str, *, after_seq: int | None = None,
                 reorder_wait_s: float = REORDER_WAIT_S) -> None:
        self.session_id = session_id
        self.queue: asyncio.Queue[dict | Encoded] = asyncio.Queue(SUBSCRIBER_QUEUE)
        """What the stream sends, in order (its reader takes from it)."""
        self.overflowed = False
        self.ending = False
        self.reorder_wait_s = reorder_wait_s
        self._last_seq: int = -1 if after_seq is None else after_seq
        """The highest seq passed on, or the last accepted before the stream began."""
        self._waiting: dict[int, dict | Encoded] = {}
        """Messages waiting, by the seq they come after."""
        self._timer: asyncio.TimerHandle | None = None

    def put(self, message: dict | Encoded) -> None:
        if self.overflowed or self.ending:
            return
        seq = message.get("seq")
        if seq is None:  # not a frame's message: what waits goes before it
            self._flush()
            self._enqueue(message)
            return
        prev = message.get("prev_seq")
        if prev is not None and prev > self._last_seq:
            self._waiting[prev] = message
            if self._timer is None:
                self._timer = asyncio.get_running_loop().call_later(
                    self.reorder_wait_s, self._flush)
            return
        self._pass(message)

    def _pass(self, message: dict | Encoded) -> None:
        self._enqueue(message)
        self._last_seq = max(message["seq"], self._last_seq)
        while (after := self._waiting.pop(self._last_seq, None)) is not None:
            self._enqueue(after)
            self._last_seq = max(self._last_seq, after["seq"])
        if not self._waiting:
            self._cancel_timer()

    def _flush(self) -> None:
        """Pass on every waiting message, in seq order."""
        self._cancel_timer()
        waiting, self._waiting = self._waiting, {}
        for message in sorted(waiting.values(), key=lambda m: m["seq"]):
            self._pass(message)

    def _cancel_timer(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def _enqueue(self, message: dict | Encoded) -> None:
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
                sub.put(GOING_AWAY)

    def subscribe(self, session_id: str, *, after_seq: int | None = None) -> Subscription:
        """A new stream's subscription (``after_seq``: see :class:`Subscription`)."""
        sub = Subscription(session_id, after_seq=after_seq)
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

    def publish(self, session_id: str, message: dict | Encoded) -> None:
        """Deliver to this process's subscribers of the session."""
        self.deliver(session_id, message)

    def deliver(self, session_id: str, message: dict | Encoded) -> None:
        for sub in list(self._subs.get(session_id, ())):
            sub.put(message)

    def close_session(self, session_id: str, ending: dict = CLOSED) -> None:
        """End the session's streams with ``ending`` (:data:`CLOSED` or :data:`EXPIRED`)."""
        self.publish(session_id, ending)
