"""``WS /v1/sessions/{id}/stream``: estimates out, and optionally frames in.

Out: a ``hello`` message once the subscription is live, then a ``frame_error`` (kind
``interrupted``) for each frame that a stopped server left unanswered and no stream has
reported yet, then one ``pose`` or ``frame_error`` message per accepted frame, in sequence
order; ``error`` (with a ``problem`` object) for a frame sent on the socket that was refused
(it gets no sequence number) or a message that could not be read; ``closed`` when the
session is deleted.

In: binary messages are frames (JPEG or PNG bytes). A text message
``{"type": "frame_meta", "seq": 12, "captured_at": "...", "metadata": {"heading_deg": 80}}``
sets the sequence number, capture time and sensor reports (as the POST's query parameters)
of the next binary frame; ``{"type": "ping"}`` is answered with ``pong``.

The token comes as ``Authorization: Bearer <token>``, as a subprotocol
(``Sec-WebSocket-Protocol: vloc, vloc.token.<token>``; the server answers ``vloc``) or,
for old clients, as ``?token=`` (redacted from the logs).

Offering the subprotocol ``vloc.geojson`` (the server answers with it) asks for every
``pose`` as a GeoJSON ``Feature`` (:mod:`app.stream.geojson`); other messages are the same.

Close codes: 4401 no token, 4403 wrong token, 4404 unknown session, 1011 the session
could not be restored, 1013 the client read too slowly, 1001 the server shuts down (after
the messages of every frame it had accepted).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import time
import uuid
from datetime import datetime

from fastapi import APIRouter, WebSocket, WebSocketDisconnect
from pydantic import BaseModel, ValidationError

from vloc.app.context import AppContext
from vloc.app.imagecheck import check_image
from vloc.app.limits import too_large
from vloc.app.problems import Problem
from vloc.app.security import TOKEN_SUBPROTOCOL, matches, presented_secret
from vloc.app.sessions.live import LiveSession
from vloc.app.sessions.schemas import Seq
from vloc.app.stream.geojson import GEOJSON_SUBPROTOCOL, as_feature
from vloc.app.stream.hub import CLOSED, GOING_AWAY, OVERFLOW, Subscription
from vloc.app.validation import check_captured_at, check_metadata

router = APIRouter(tags=["stream"])


class FrameMeta(BaseModel):
    type: str
    seq: Seq | None = None
    captured_at: datetime | None = None
    metadata: dict[str, float | None] | None = None
    """The frame's sensor reports, by the names of the POST's query parameters."""


@router.websocket("/v1/sessions/{session_id}/stream")
async def stream(websocket: WebSocket, session_id: str) -> None:
    ctx: AppContext = websocket.app.state.ctx
    secret = presented_secret(websocket)
    offered = websocket.scope.get("subprotocols", ())
    geojson = GEOJSON_SUBPROTOCOL in offered
    accepted = GEOJSON_SUBPROTOCOL if geojson else (
        TOKEN_SUBPROTOCOL if TOKEN_SUBPROTOCOL in offered else None)
    await websocket.accept(subprotocol=accepted)
    live = await _authorise(websocket, ctx, session_id, secret)
    if live is None:
        return
    # Taken before subscribing: they come before any frame this stream will see.
    interrupted = await ctx.runtime.interrupted(live)
    sub = ctx.hub.subscribe(live.id, after_seq=live.last_seq)
    ctx.metrics.stream_subscribers.inc()
    sender = asyncio.create_task(_send_loop(websocket, sub, as_feature if geojson else None))
    try:
        await ctx.hub.ready(live.id)
        sub.put({"type": "hello", "session_id": live.id, "last_seq": live.last_seq})
        for msg in interrupted:
            sub.put(msg)
        await _receive_loop(websocket, ctx, live, sub)
    except WebSocketDisconnect:
        pass
    finally:
        sender.cancel()
        with contextlib.suppress(asyncio.CancelledError, Exception):
            await sender
        ctx.hub.unsubscribe(sub)
        ctx.metrics.stream_subscribers.dec()


async def _authorise(websocket: WebSocket, ctx: AppContext, session_id: str,
                     secret: str | None) -> LiveSession | None:
    if secret is None:
        await websocket.close(4401, "a session token is required (Authorization: Bearer)")
        return None
    try:
        live = await ctx.runtime.get(uuid.UUID(session_id))
    except ValueError:
        live = None
    except Problem as p:
        await websocket.close(1011, p.detail[:120])
        return None
    if live is None:
        await websocket.close(4404, f"session {session_id} does not exist")
        return None
    if not (matches(secret, live.token_hash) or matches(secret, ctx.admin_key_hash)):
        await websocket.close(4403, "this token does not open this session")
        return None
    return live


async def _send_loop(websocket: WebSocket, sub: Subscription, encode=None) -> None:
    """The only writer of the socket: everything it sends goes through the subscription
    (and ``encode``, where the client asked for another form of the messages)."""
    while True:
        msg = await sub.get()
        if msg is OVERFLOW:
            await websocket.close(1013, "the client reads too slowly")
            return
        if msg is GOING_AWAY:
            await websocket.close(1001, "the server is shutting down")
            return
        await websocket.send_text(json.dumps(encode(msg) if encode else msg))
        if msg.get("type") == CLOSED["type"]:
            await websocket.close(1000, "session deleted")
            return


async def _receive_loop(websocket: WebSocket, ctx: AppContext, live: LiveSession,
                        sub: Subscription) -> None:
    meta = FrameMeta(type="frame_meta")
    while True:
        message = await websocket.receive()
        if message["type"] == "websocket.disconnect":
            return
        if message.get("bytes") is not None:
            await _frame(ctx, live, sub, message["bytes"], meta)
            meta = FrameMeta(type="frame_meta")
        elif message.get("text") is not None:
            meta = _text(sub, message["text"], meta)


async def _frame(ctx: AppContext, live: LiveSession, sub: Subscription, data: bytes,
                 meta: FrameMeta) -> None:
    t0 = time.perf_counter()
    try:
        if len(data) > ctx.settings.max_frame_bytes:
            raise too_large(ctx.settings.max_frame_bytes)
        check_image(data, max_pixels=ctx.settings.max_pixels)
        captured = check_captured_at(meta.captured_at)
        metadata = check_metadata(meta.metadata or {})
        _, queued = await ctx.runtime.accept(live, data, seq=meta.seq, captured_at=captured,
                                             t0=t0, metadata=metadata)
    except Problem as p:
        ctx.metrics.frames_rejected.labels(p.kind or "bad-image").inc()
        sub.put({"type": "error", "problem": p.body()})
        return
    queued.add_done_callback(lambda f: _report_refusal(sub, f))


def _report_refusal(sub: Subscription, queued: asyncio.Future) -> None:
    """A frame whose record failed was not processed: say so as for any refused frame."""
    if (p := queued.exception()) is not None:
        sub.put({"type": "error", "problem": p.body()})


def _text(sub: Subscription, text: str, meta: FrameMeta) -> FrameMeta:
    try:
        parsed = FrameMeta.model_validate_json(text)
    except ValidationError as exc:
        problem = Problem(422, f"unreadable message: {exc.errors()[0]['msg']}",
                          kind="bad-message")
        sub.put({"type": "error", "problem": problem.body()})
        return meta
    if parsed.type == "ping":
        sub.put({"type": "pong"})
        return meta
    if parsed.type == "frame_meta":
        return parsed
    problem = Problem(422, f"unknown message type {parsed.type!r}", kind="bad-message")
    sub.put({"type": "error", "problem": problem.body()})
    return meta
