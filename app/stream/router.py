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

Close codes (docs/api.md, "Close codes"; a ``44xx`` code is the HTTP status the session's
routes answer with, plus 4000), each with a reason that starts with its slug:

- 4401 ``unauthorized``: no token; 4403 ``forbidden``: a token that does not open it;
- 4404 ``not-found``: no such session; ``session-deleted``: deleted while the stream was
  open (after a ``closed`` message);
- 4410 ``session-expired``: it expired after its time to live (at the handshake, or while
  open after a ``closed`` message);
- 1001 ``server-shutdown``: the server is stopping (after the messages of every frame it
  had accepted);
- 1011 ``session-unavailable``: the session could not be restored;
- 1013 ``too-slow``: the client read too slowly.
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
from vloc.app.problems import Problem, ProblemKind
from vloc.app.security import TOKEN_SUBPROTOCOL, matches, presented_secret
from vloc.app.sessions.live import LiveSession
from vloc.app.sessions.registry import expired_problem
from vloc.app.sessions.schemas import Seq
from vloc.app.stream.geojson import GEOJSON_SUBPROTOCOL, as_feature
from vloc.app.stream.hub import CLOSED, GOING_AWAY, OVERFLOW, Encoded, Subscription
from vloc.app.validation import check_captured_at, check_metadata

router = APIRouter(tags=["stream"])

MAX_REASON_BYTES = 123
"""The longest close reason a WebSocket close frame carries (RFC 6455, 5.5)."""

ENDINGS = {"session-deleted": 4404, "session-expired": 4410}
"""The close code after a ``closed`` message, by its ``kind``."""


def close_reason(slug: str, text: str) -> str:
    """``"<slug>: <text>"`` cut at a word to fit a close frame."""
    reason = f"{slug}: {text}"
    if len(reason.encode()) <= MAX_REASON_BYTES:
        return reason
    cut = reason.encode()[:MAX_REASON_BYTES - 3].decode("utf-8", "ignore")
    return cut.rsplit(" ", 1)[0].rstrip(",;:") + "..."


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
    interrupted = await ctx.sessions.interrupted(live)
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
        await websocket.close(4401, close_reason(
            "unauthorized", "a session token is required (Authorization: Bearer)"))
        return None
    try:
        live = await ctx.sessions.get(uuid.UUID(session_id))
    except ValueError:
        live = None
    except Problem as p:
        if p.status == 410:
            await websocket.close(4410, close_reason("session-expired", p.detail))
        else:
            await websocket.close(1011, close_reason("session-unavailable", p.detail))
        return None
    if live is None:
        await websocket.close(4404, close_reason("not-found",
                                                 f"session {session_id} does not exist"))
        return None
    if not (matches(secret, live.token_hash) or matches(secret, ctx.admin_key_hash)):
        await websocket.close(4403, close_reason(
            "forbidden", "this token does not open this session"))
        return None
    if live.expired() and not live.arrivals:  # as its HTTP routes would answer 410
        await ctx.sessions.expire(live)
        await websocket.close(4410, close_reason("session-expired",
                                                 expired_problem(session_id).detail))
        return None
    return live


async def _send_loop(websocket: WebSocket, sub: Subscription, encode=None) -> None:
    """The only writer of the socket: everything it sends goes through the subscription
    (and ``encode``, where the client asked for another form of the messages)."""
    while True:
        msg = await sub.queue.get()
        if msg is OVERFLOW:
            await websocket.close(1013, close_reason("too-slow", "the client reads too slowly"))
            return
        if msg is GOING_AWAY:
            await websocket.close(1001, close_reason(
                "server-shutdown", "the server is stopping; reconnect once it is back"))
            return
        if encode is not None:  # another form: made from the message's fields
            text = json.dumps(encode(msg.fields() if isinstance(msg, Encoded) else msg))
        else:
            text = msg.text if isinstance(msg, Encoded) else json.dumps(msg)
        await websocket.send_text(text)
        if msg.get("type") == CLOSED["type"]:
            kind = msg.get("kind", CLOSED["kind"])
            await websocket.close(ENDINGS[kind], close_reason(kind, msg["reason"]))
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
        header = check_image(data, max_pixels=ctx.settings.max_pixels)
        captured = check_captured_at(meta.captured_at)
        metadata = check_metadata(meta.metadata or {})
        _, queued = await ctx.intake.accept(live, data, seq=meta.seq, captured_at=captured,
                                            t0=t0, metadata=metadata, header=header)
    except Problem as p:
        ctx.metrics.frames_rejected.labels(p.kind or ProblemKind.BAD_IMAGE).inc()
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
                          kind=ProblemKind.BAD_MESSAGE)
        sub.put({"type": "error", "problem": problem.body()})
        return meta
    if parsed.type == "ping":
        sub.put({"type": "pong"})
        return meta
    if parsed.type == "frame_meta":
        return parsed
    problem = Problem(422, f"unknown message type {parsed.type!r}", kind=ProblemKind.BAD_MESSAGE)
    sub.put({"type": "error", "problem": problem.body()})
    return meta
