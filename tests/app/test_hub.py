"""A stream's subscription puts back in order the frames' messages that reach it out of the
order their worker answered them (``prev_seq``), as several replicas publishing one
session's poses can deliver them."""

from __future__ import annotations

import asyncio
import json
import uuid

from vloc.app.sessions.schemas import FrameError
from vloc.app.stream.hub import CLOSED, Encoded, LocalHub, Subscription


def _pose(seq: int, prev: int | None) -> dict:
    msg = {"type": "pose", "seq": seq}
    return msg if prev is None else msg | {"prev_seq": prev}


def _drain(sub: Subscription) -> list:
    out = []
    while not sub.queue.empty():
        msg = sub.queue.get_nowait()
        out.append(msg.get("seq", msg["type"]))
    return out


def _run(coro):
    return asyncio.run(coro)


def test_messages_in_order_pass_at_once():
    async def go():
        sub = Subscription("s")
        for seq in range(4):
            sub.put(_pose(seq, seq - 1 if seq else None))
        return _drain(sub)

    assert _run(go()) == [0, 1, 2, 3]


def test_a_message_waits_for_the_one_it_comes_after():
    async def go():
        sub = Subscription("s", reorder_wait_s=5.0)
        sub.put(_pose(0, None))
        sub.put(_pose(2, 1))
        sub.put(_pose(3, 2))
        held = _drain(sub)
        sub.put(_pose(1, 0))
        return held, _drain(sub)

    held, after = _run(go())
    assert held == [0]
    assert after == [1, 2, 3]


def test_numbers_chosen_by_the_client_with_gaps_are_chained_by_prev_seq():
    async def go():
        sub = Subscription("s", reorder_wait_s=5.0)
        sub.put(_pose(10, None))
        sub.put(_pose(40, 25))
        sub.put(_pose(25, 10))
        return _drain(sub)

    assert _run(go()) == [10, 25, 40]


def test_a_predecessor_that_never_comes_is_given_up_after_the_wait():
    async def go():
        sub = Subscription("s", reorder_wait_s=0.05)
        sub.put(_pose(0, None))
        sub.put(_pose(3, 2))
        sub.put(_pose(2, 1))
        early = _drain(sub)
        await asyncio.sleep(0.2)
        late = _drain(sub)
        sub.put(_pose(1, 0))  # too late for its place: passed on, not lost
        sub.put(_pose(4, 3))  # 3 was passed on: no wait
        return early, late, _drain(sub)

    assert _run(go()) == ([0], [2, 3], [1, 4])


def test_a_message_that_is_not_a_frames_passes_what_waits_before_it():
    async def go():
        hub = LocalHub()
        sub = hub.subscribe("s")
        sub.reorder_wait_s = 5.0
        hub.publish("s", _pose(0, None))
        hub.publish("s", _pose(2, 1))
        hub.close_session("s")
        return _drain(sub)

    assert _run(go()) == [0, 2, CLOSED["type"]]


def test_a_stream_opened_before_any_frame_waits_for_the_first():
    # The second frame's pose (published by the replica that holds the stream) overtakes
    # the first's (published by the other one).
    async def go():
        sub = Subscription("s", after_seq=None, reorder_wait_s=5.0)
        sub.put(_pose(1, 0))
        held = _drain(sub)
        sub.put(_pose(0, None))
        return held, _drain(sub)

    assert _run(go()) == ([], [0, 1])


def test_a_late_subscriber_waits_for_nothing_accepted_before_it_began():
    async def go():
        sub = Subscription("s", after_seq=6, reorder_wait_s=5.0)
        sub.put(_pose(7, 6))   # 6 was answered before the stream began
        sub.put(_pose(9, 8))   # 8 came after: waited for
        held = _drain(sub)
        sub.put(_pose(8, 7))
        return held, _drain(sub)

    assert _run(go()) == ([7], [8, 9])


def test_a_frame_message_is_written_once_and_its_order_added_to_that_text():
    """The stream's copy of a message is its text with ``prev_seq`` appended, not the
    message written again; a copy received through Redis keeps the text it came with."""
    error = FrameError(session_id=uuid.uuid4(), seq=7, captured_at=None, kind="bad_image",
                       reason="not an \u00e9 image", latency_ms=3.25)
    message = Encoded.of(error)
    assert json.loads(message.text) == error.model_dump(mode="json")
    assert (message["type"], message["seq"], message["kind"]) == ("frame_error", 7, "bad_image")
    streamed = message.after(6)
    assert json.loads(streamed.text) == error.model_dump(mode="json") | {"prev_seq": 6}
    assert streamed["prev_seq"] == 6 and "prev_seq" not in message
    received = Encoded.received(streamed.text)
    assert received.text is streamed.text and received.fields() == json.loads(streamed.text)

    async def go():
        sub = Subscription("s", after_seq=5)
        sub.put(Encoded.received(message.after(6).text))  # waits for frame 6
        sub.put(_pose(6, 5))
        return _drain(sub)

    assert _run(go()) == [6, 7]
