"""Frame sequence numbers and the frames table: seq bounds at the edge, storage isolated
per row, frames left queued by a stopped server reported, no seq ever reused."""

from __future__ import annotations

import time
import uuid
from dataclasses import replace
from datetime import UTC, datetime

from fastapi.testclient import TestClient
from sqlalchemy import select

from tests.app.conftest import ADMIN, FAST, PROBLEM, build_map, service_settings, snapshot
from tests.app.test_sessions import open_stream, post_frame
from vloc.app.main import create_app
from vloc.app.sessions.models import Frame, FrameStatus
from vloc.app.sessions.pose import FrameContext, from_estimate
from vloc.app.sessions.schemas import MAX_SEQ
from vloc.app.sessions.store import FrameRecord, OutcomeRecord
from vloc.app.stream.hub import Encoded
from vloc.workers.core.estimate import Estimate, Status
from vloc.workers.engine import FrameDone

TIMEOUT = 60


def test_seq_bounds_over_http(service, shots):
    c = service.client
    sid, auth = service.new_session()
    frame = shots[1][0].jpeg
    before = snapshot(c)
    for bad in (-1, MAX_SEQ + 1, 2**64 + 3):
        r = post_frame(c, sid, frame, auth, seq=bad)
        assert r.status_code == 422 and r.headers["content-type"] == PROBLEM, r.text
        assert r.json()["type"] == "urn:vloc:problem:validation"
    assert snapshot(c) == before
    r = post_frame(c, sid, frame, auth, seq=MAX_SEQ, wait="true")
    assert r.status_code == 200 and r.json()["seq"] == MAX_SEQ, r.text
    before = snapshot(c)
    r = post_frame(c, sid, frame, auth)
    assert r.status_code == 409 and r.json()["type"] == "urn:vloc:problem:seq-exhausted"
    assert snapshot(c) == before
    (pose,) = c.get(f"/v1/sessions/{sid}/poses", headers=auth).json()
    assert (pose["type"], pose["seq"]) == ("pose", MAX_SEQ)


def test_seq_bounds_over_the_websocket(service, shots):
    c = service.client
    sid, auth = service.new_session()
    frame = shots[1][0].jpeg
    with open_stream(c, sid, auth) as ws:
        ws.receive_json()
        for meta in ({"seq": MAX_SEQ + 11}, {"seq": -1}, {"seq": "12"}, {"seq": 1.5}):
            ws.send_json({"type": "frame_meta", **meta})
            error = ws.receive_json()
            assert error["type"] == "error", meta
            assert error["problem"]["type"] == "urn:vloc:problem:bad-message"
        # A refused frame_meta numbers nothing: the next frame takes the next seq.
        ws.send_bytes(frame)
        assert ws.receive_json()["seq"] == 0
        ws.send_json({"type": "frame_meta", "seq": MAX_SEQ})
        ws.send_bytes(frame)
        assert ws.receive_json()["seq"] == MAX_SEQ
    s = settled(c, sid, auth)
    assert (s["last_seq"], s["frames_processed"], s["frames_failed"]) == (MAX_SEQ, 2, 0)


def test_a_session_read_with_nothing_pending_counts_every_frame_stored(service, shots):
    """The frames pending are counted before the session's counters are read: a frame
    stored in between (by the writer thread) is in the counters once it is no longer
    pending, so a reader waiting for ``frames_pending == 0`` sees it."""
    from vloc.app.sessions import service as sessions_service
    from vloc.app.sessions.models import LocalisationSession

    c = service.client
    sid, auth = service.new_session()
    assert post_frame(c, sid, shots[1][0].jpeg, auth, wait="true").status_code == 200
    ctx = c.app.state.ctx

    class StoredMeanwhile:
        """A registry whose last frame is stored just as its pending frames are counted."""

        def pending(self, session_id):
            with ctx.db_sessions() as other:
                row = other.get(LocalisationSession, session_id)
                row.frames_processed += 1
                row.last_seq = 1
                other.commit()
            return 0

    with ctx.db_sessions() as db:
        row = db.get(LocalisationSession, uuid.UUID(sid))
        assert (row.frames_processed, row.last_seq) == (1, 0)  # read before the store
        read = sessions_service.read_session(db, row=row, sessions=StoredMeanwhile())
    assert (read.frames_pending, read.frames_processed, read.last_seq) == (0, 2, 1)


def settled(client, sid: str, auth: dict) -> dict:
    """The session once every frame it accepted is stored (the stream runs ahead)."""
    deadline = time.monotonic() + TIMEOUT
    while (s := client.get(f"/v1/sessions/{sid}", headers=auth).json())["frames_pending"] \
            and time.monotonic() < deadline:
        time.sleep(0.02)
    return s


def _estimate_message(session_id: str, seq: int, **change) -> tuple:
    """A frame's outcome with its message and row, as the intake hands them to the store."""
    estimate = Estimate(**{"x": 1.0, "y": 2.0, "lat": 41.0, "lon": -83.0, "sigma_x": 1.0,
                           "sigma_y": 1.0, "cov": (1.0, 0.0, 0.0, 1.0), "feature": "sift",
                           "next_feature": "sift", "n_particles": 60,
                           "status": Status.TRACKING, "best_image": 3,
                           "processing_ms": 5.0} | change)
    ctx = FrameContext(session_id=session_id, seq=seq, map_id=str(uuid.uuid4()),
                       map_revision=1, map_folder="", captured_at=None,
                       received_at=datetime.now(UTC), metadata=None, decode_ms=1.0,
                       latency_ms=9.0)
    message, row = from_estimate(estimate, ctx, bound_m=25.0, converged_before=False)
    return FrameDone(session_id, seq, estimate, None, 1.0), Encoded.of(message), row


def test_a_row_the_database_refuses_costs_only_that_row(service):
    """Two sessions' frames in one batch; one row of one of them cannot be stored."""
    c = service.client
    a, _ = service.new_session()
    b, b_auth = service.new_session()
    now = datetime.now(UTC)
    good_a, good_b = _estimate_message(a, 0), _estimate_message(b, 0)
    bad_b = _estimate_message(b, 1, n_particles=2**63)  # out of range for its column
    batch = [FrameRecord(a, 0, now, None), FrameRecord(b, 0, now, None),
             FrameRecord(b, 1, now, None), FrameRecord(b, MAX_SEQ + 9, now, None),
             OutcomeRecord(*good_a), OutcomeRecord(*bad_b), OutcomeRecord(*good_b)]
    refused = c.app.state.ctx.intake.store.write(batch)
    assert sorted(refused) == [3, 5]
    with c.app.state.ctx.db_sessions() as db:
        frames = {(str(f.session_id), f.seq): f.status for f in db.scalars(select(Frame).where(
            Frame.session_id.in_([uuid.UUID(a), uuid.UUID(b)])))}
    assert frames == {(a, 0): "answered", (b, 0): "answered", (b, 1): "queued"}
    assert [p["seq"] for p in c.get(f"/v1/sessions/{b}/poses", headers=b_auth).json()] == [0]
    s = c.get(f"/v1/sessions/{b}", headers=b_auth).json()
    assert (s["frames_processed"], s["last_seq"]) == (1, 0)


def test_an_estimate_that_cannot_be_stored_is_reported_not_stored(service, shots, tmp_path):
    """The outcomes of one session cannot be stored (a fault injected between the engine and
    the intake); another session's frames, processed at the same time, are all stored."""
    c = service.client
    ctx = c.app.state.ctx
    a, a_auth = service.new_session()
    b, b_auth = service.new_session()
    deliver = ctx.engine.on_outcome

    def corrupt(outcome):
        if isinstance(outcome, FrameDone) and outcome.session_id == a:
            outcome = FrameDone(a, outcome.seq, replace(outcome.estimate, n_particles=2**63),
                                outcome.state, outcome.decode_ms)
        deliver(outcome)

    release = tmp_path / "release"
    ctx.engine.on_outcome = corrupt
    try:
        held = ctx.engine.call("tests.engine.fakes:wait_for_file", str(release))
        with open_stream(c, a, a_auth) as ws:
            ws.receive_json()
            assert post_frame(c, a, shots[1][0].jpeg, a_auth).json() == {"seq": 0}
            for q in shots[1][:3]:
                assert post_frame(c, b, q.jpeg, b_auth).status_code == 202
            release.touch()
            assert held.result(TIMEOUT)
            streamed = [ws.receive_json() for _ in range(2)]
            r = post_frame(c, a, shots[1][1].jpeg, a_auth, wait="true")
    finally:
        ctx.engine.on_outcome = deliver
        release.touch()
    assert [(m["type"], m["seq"]) for m in streamed] == [("pose", 0), ("frame_error", 0)]
    assert streamed[1]["kind"] == "not_stored"
    assert r.status_code == 500 and r.json()["type"] == "urn:vloc:problem:frame-not-stored"
    stored = c.get(f"/v1/sessions/{a}/poses", headers=a_auth).json()
    assert [(m["type"], m["seq"], m.get("kind")) for m in stored] == [
        ("frame_error", 0, "not_stored"), ("frame_error", 1, "not_stored")]
    s = c.get(f"/v1/sessions/{a}", headers=a_auth).json()
    assert (s["last_seq"], s["frames_processed"], s["frames_failed"]) == (1, 0, 2)
    poses = c.get(f"/v1/sessions/{b}/poses", headers=b_auth).json()
    assert [(p["type"], p["seq"]) for p in poses] == [("pose", 0), ("pose", 1), ("pose", 2)]


def test_a_frame_that_cannot_be_recorded_is_refused_and_keeps_its_seq_free(service, shots):
    c = service.client
    ctx = c.app.state.ctx
    sid, auth = service.new_session()
    assert post_frame(c, sid, shots[1][0].jpeg, auth, wait="true").status_code == 200
    live = c.portal.call(ctx.sessions.get, uuid.UUID(sid))
    # Past the edge's bound, as a caller that skipped it would: the record is refused.
    seq, queued = c.portal.call(lambda: ctx.intake.accept(
        live, shots[1][1].jpeg, seq=MAX_SEQ + 1, captured_at=None, t0=0.0))
    assert seq == MAX_SEQ + 1
    problem = _failure(c, queued)
    assert (problem.status, problem.kind) == (503, "storage-unavailable")
    r = post_frame(c, sid, shots[1][1].jpeg, auth, wait="true")
    assert r.status_code == 200 and r.json()["seq"] == 1
    s = c.get(f"/v1/sessions/{sid}", headers=auth).json()
    assert (s["last_seq"], s["frames_processed"], s["frames_failed"]) == (1, 2, 0)


def _failure(client, fut):
    """The exception a loop future ends with (awaited on the app's loop)."""
    async def outcome():
        try:
            await fut
        except Exception as exc:  # noqa: BLE001 - the value under test
            return exc
        return None

    return client.portal.call(outcome)


def _insert_queued(ctx, session_id: str, seqs, owner: str) -> None:
    with ctx.db_sessions() as db:
        for seq in seqs:
            db.add(Frame(session_id=uuid.UUID(session_id), seq=seq, status=FrameStatus.QUEUED,
                         owner=owner, received_at=datetime.now(UTC)))
        db.commit()


def test_frames_left_queued_are_reported_once_and_their_seqs_never_reused(
        tmp_path, database_url, shots):
    settings = service_settings(tmp_path / "data", database_url, instance_name="api-1")
    q = shots[1]
    with TestClient(create_app(settings)) as c:
        map_id = build_map(c, shots[0][:6])
        r = c.post("/v1/sessions", headers=ADMIN,
                   json={"map_id": map_id, "params": FAST, "seed": 2})
        sid, auth = r.json()["id"], {"Authorization": f"Bearer {r.json()['token']}"}
        for shot in q[:2]:
            assert post_frame(c, sid, shot.jpeg, auth, wait="true").status_code == 200
    # What a server killed with frames queued leaves behind: its own (api-1) and, for the
    # same session, those of another server that held it before (api-0).
    with TestClient(create_app(settings)) as c:
        _insert_queued(c.app.state.ctx, sid, [2, 3, 4], "api-1")
        _insert_queued(c.app.state.ctx, sid, [5], "api-0")
    with TestClient(create_app(settings)) as c:
        s = c.get(f"/v1/sessions/{sid}", headers=auth).json()
        assert (s["last_seq"], s["frames_processed"], s["frames_failed"]) == (4, 2, 3)
        listed = c.get(f"/v1/sessions/{sid}/poses", headers=auth).json()
        assert [(m["type"], m["seq"]) for m in listed] == [
            ("pose", 0), ("pose", 1), ("frame_error", 2), ("frame_error", 3),
            ("frame_error", 4)]
        assert {m["kind"] for m in listed[2:]} == {"interrupted"}
        assert listed[2]["latency_ms"] is None and listed[2]["reason"]
        with open_stream(c, sid, auth) as ws:
            hello = ws.receive_json()
            reported = [ws.receive_json() for _ in range(4)]
            r = post_frame(c, sid, q[2].jpeg, auth, wait="true")
            assert ws.receive_json()["seq"] == 6
        assert hello["last_seq"] == 5
        assert [(m["type"], m["seq"], m["kind"]) for m in reported] == [
            ("frame_error", seq, "interrupted") for seq in (2, 3, 4, 5)]
        assert r.status_code == 200 and r.json()["seq"] == 6
        # Reported once: a second stream starts with the next frame.
        with open_stream(c, sid, auth) as ws:
            assert ws.receive_json()["type"] == "hello"
            assert post_frame(c, sid, q[3].jpeg, auth).json() == {"seq": 7}
            assert ws.receive_json()["seq"] == 7
        listed = c.get(f"/v1/sessions/{sid}/poses", headers=auth,
                       params={"after_seq": 1, "limit": 5}).json()
        assert [m["seq"] for m in listed] == [2, 3, 4, 5, 6]
        s = settled(c, sid, auth)
        assert (s["last_seq"], s["frames_processed"], s["frames_failed"]) == (7, 4, 4)
        with c.app.state.ctx.db_sessions() as db:
            statuses = dict(db.execute(select(Frame.seq, Frame.status)
                                       .where(Frame.session_id == uuid.UUID(sid))).all())
    assert statuses == {0: "answered", 1: "answered", 2: "failed", 3: "failed", 4: "failed",
                        5: "failed", 6: "answered", 7: "answered"}
