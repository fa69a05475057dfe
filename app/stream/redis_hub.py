"""Fan-out through Redis pub/sub, for several API replicas behind one load balancer.

A frame is processed by the replica that accepted it; its estimate is published on the
channel ``vloc:session:<id>`` (the message's JSON as the replica wrote it) and every replica
delivers it to its own subscribers of that session, sending that same text. Publishing goes through one task, so a session's messages keep their order.
"""

from __future__ import annotations

import asyncio
import json
import logging

import redis.asyncio as aioredis

from vloc.app.stream.hub import Encoded, LocalHub

log = logging.getLogger(__name__)

CHANNEL_PREFIX = "vloc:session:"


class RedisHub(LocalHub):
    def __init__(self, url: str) -> None:
        super().__init__()
        self.url = url
        self._redis: aioredis.Redis | None = None
        self._pubsub = None
        self._outbox: asyncio.Queue[tuple[str, str] | None] = asyncio.Queue()
        self._tasks: list[asyncio.Task] = []
        self._channels: dict[str, asyncio.Event] = {}

    async def start(self) -> None:
        self._redis = aioredis.from_url(self.url)
        await self._redis.ping()
        self._pubsub = self._redis.pubsub()
        # A pub/sub connection needs one subscription before it can be listened to.
        await self._pubsub.subscribe(CHANNEL_PREFIX + "_")
        self._tasks = [asyncio.create_task(self._publisher(), name="redis-publisher"),
                       asyncio.create_task(self._listener(), name="redis-listener")]

    async def stop(self) -> None:
        await super().stop()
        await self._outbox.put(None)
        await asyncio.gather(self._tasks[0], return_exceptions=True)
        self._tasks[1].cancel()
        await asyncio.gather(self._tasks[1], return_exceptions=True)
        if self._pubsub is not None:
            await self._pubsub.aclose()
        if self._redis is not None:
            await self._redis.aclose()

    def subscribe(self, session_id: str, *, after_seq: int | None = None):
        sub = super().subscribe(session_id, after_seq=after_seq)
        channel = CHANNEL_PREFIX + session_id
        if channel not in self._channels:
            self._channels[channel] = asyncio.Event()
            self._background(self._pubsub.subscribe(channel))
        return sub

    def unsubscribe(self, sub) -> None:
        super().unsubscribe(sub)
        channel = CHANNEL_PREFIX + sub.session_id
        if sub.session_id not in self._subs and channel in self._channels:
            del self._channels[channel]
            self._background(self._pubsub.unsubscribe(channel))

    async def ready(self, session_id: str, timeout: float = 5.0) -> None:
        """Wait until Redis has confirmed this replica's subscription to the session."""
        event = self._channels.get(CHANNEL_PREFIX + session_id)
        if event is not None:
            await asyncio.wait_for(event.wait(), timeout)

    def publish(self, session_id: str, message: dict | Encoded) -> None:
        text = message.text if isinstance(message, Encoded) else json.dumps(message)
        self._outbox.put_nowait((CHANNEL_PREFIX + session_id, text))

    async def _publisher(self) -> None:
        while (item := await self._outbox.get()) is not None:
            try:
                await self._redis.publish(*item)
            except Exception:  # noqa: BLE001 - a Redis hiccup loses a message, not the hub
                log.exception("redis publish failed")

    async def _listener(self) -> None:
        while True:
            try:
                msg = await self._pubsub.get_message(timeout=1.0)
            except Exception:  # noqa: BLE001 - reconnects on the next call
                log.exception("redis listen failed")
                await asyncio.sleep(0.5)
                continue
            if msg is None:
                continue
            channel = msg["channel"].decode()
            if msg.get("type") == "subscribe":
                if (event := self._channels.get(channel)) is not None:
                    event.set()
                continue
            if msg.get("type") != "message":
                continue
            # read once here, never written again: the sockets send the text received
            self.deliver(channel.removeprefix(CHANNEL_PREFIX),
                         Encoded.received(msg["data"].decode()))

    def _background(self, coro) -> None:
        task = asyncio.get_running_loop().create_task(coro)
        task.add_done_callback(lambda t: t.exception() and log.error(
            "redis subscription change failed: %s", t.exception()))
