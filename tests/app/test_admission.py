"""Server-wide admission of frames: bounds on the frames and bytes the API process holds
(503 server-busy), shared fairly between sessions (429 over-fair-share), both with
Retry-After; a refused frame changes nothing and the session goes on once there is room."""

from __future__ import annotations

import concurrent.futures
from collections.abc import Iterator

import pytest

from tests.app.conftest import ADMIN, FAST, PROBLEM, backend_client, build_map, snapshot
from tests.app.test_sessions import post_frame
from vloc.app.problems import Problem
from vloc.app.sessions.budget import FrameBudget, Held

MAX_FRAMES = 8


@pytest.fixture(scope="module", params=["sqlite", pytest.param("postgres",
                                                                marks=pytest.mark.postgres)])
def busy(request, tmp_path_factory, shots) -> Iterator[tuple]:
    """An app that holds at most MAX_FRAMES frames, with a built map."""
    for c in backend_client(request.param, tmp_path_factory, max_queued_frames=MAX_FRAMES):
        yield c, build_map(c, shots[0][:4])


@pytest.fixture
def hold(busy, tmp_path) -> Iterator[callable]:
    """``hold()`` keeps the app's one worker busy until the test ends: frames stay queued."""
    c, _ = busy
    release = tmp_path / "release"
    held = []
    yield lambda: held.append(c.app.state.ctx.engine.call(
        "tests.engine.fakes:wait_for_file", str(release)))
    release.touch()
    concurrent.futures.wait(held, 60)


def _session(c, map_id) -> tuple[str, dict]:
    r = c.post("/v1/sessions", json={"map_id": map_id, "params": FAST}, headers=ADMIN)
    assert r.status_code == 201, r.text
    return r.json()["id"], {"Authorization": f"Bearer {r.json()['token']}"}


def _refused(r, status: int, kind: str) -> None:
    assert r.status_code == status, r.text
    assert r.headers["content-type"] == PROBLEM and r.headers["retry-after"] == "1"
    assert r.json()["type"] == f"urn:vloc:problem:{kind}"


def test_a_full_server_answers_503_and_a_greedy_session_429(busy, shots, hold):
    c, map_id = busy
    (greedy, g_auth), (other, o_auth) = _session(c, map_id), _session(c, map_id)
    hold()
    frame = shots[1][0].jpeg
    # alone, a session may fill the server past half (its share is all of it)
    assert [post_frame(c, greedy, frame, g_auth).status_code for _ in range(5)] == [202] * 5
    # the other's frame fits its share; the greedy one is past its share (8 / 2)
    assert post_frame(c, other, frame, o_auth).status_code == 202
    before = snapshot(c)
    _refused(post_frame(c, greedy, frame, g_auth), 429, "over-fair-share")
    assert snapshot(c) == before
    assert [post_frame(c, other, frame, o_auth).status_code for _ in range(2)] == [202] * 2
    # 8 held: every session is refused now, whatever its share
    before = snapshot(c)
    r = post_frame(c, other, frame, o_auth)
    _refused(r, 503, "server-busy")
    assert r.json()["max_queued_frames"] == MAX_FRAMES
    assert snapshot(c) == before
    reads = [c.get(f"/v1/sessions/{s}", headers=a).json() for s, a in
             ((greedy, g_auth), (other, o_auth))]
    assert [r["frames_pending"] for r in reads] == [5, 3]


def test_room_comes_back_as_frames_are_answered(busy, shots):
    c, map_id = busy
    sid, auth = _session(c, map_id)
    frame = shots[1][0].jpeg
    for _ in range(3 * MAX_FRAMES):  # more than the bound, one at a time
        r = post_frame(c, sid, frame, auth, wait="true")
        assert r.status_code == 200, r.text


def test_the_byte_bound_and_the_fair_share_of_bytes():
    accepted: dict[str, Held] = {}
    budget = FrameBudget(max_bytes=1000, max_frames=100, accepted=lambda: accepted)
    with budget.reading("a", 400):  # a body being read counts
        with pytest.raises(Problem) as busy:
            budget.check("b", 601)
        assert (busy.value.status, busy.value.kind) == (503, "server-busy")
        budget.check("b", 500)  # its share of two sessions
    accepted.update(a=Held(1, 600), b=Held(1, 100))
    with pytest.raises(Problem) as unfair:
        budget.check("a", 1)  # past half of 1000 and past its share, 500 of 2 sessions
    assert (unfair.value.status, unfair.value.kind) == (429, "over-fair-share")
    budget.check("b", 300)
    assert budget.held() == {"a": Held(1, 600), "b": Held(1, 100)}
