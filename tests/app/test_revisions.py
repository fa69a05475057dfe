"""A map's revisions through the real app: listed with what changed, restored with the answers
they gave, dropped with their files, on SQLite and PostgreSQL."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from tests.app.conftest import (
    ADMIN,
    FAST,
    PROBLEM,
    UNKNOWN_ID,
    backend_client,
    jpeg_files,
    snapshot,
    wait_job,
)
from vloc.workers.core.rowchunks import chunk_bounds

JPEG = {**ADMIN, "Content-Type": "image/jpeg"}
ANSWER = ("lat", "lon", "x", "y", "cov", "feature", "measurement", "image_filename",
          "map_revision", "horizontal_accuracy_m")
"""The fields of a single-image localisation that depend on the map, not on timing."""


@pytest.fixture(scope="module",
                params=["sqlite", pytest.param("postgres", marks=pytest.mark.postgres)])
def module_client(request, tmp_path_factory):
    """The app with a revision's local features in files of about two images each, so that
    a ten-image map's update leaves some of them as they were."""
    yield from backend_client(request.param, tmp_path_factory, map_chunk_images=2)


def _build(c, map_id: str) -> dict:
    job = wait_job(c, c.post(f"/v1/maps/{map_id}/build", headers=ADMIN).json()["job_id"])
    assert job["status"] == "done", job
    return job


def _answers(c, map_id: str, queries) -> list[dict]:
    out = []
    for q in queries:
        r = c.post(f"/v1/maps/{map_id}/localize", content=q.jpeg, headers=JPEG,
                   params={"seed": 3})
        assert r.status_code == 200, r.text
        out.append({k: r.json()[k] for k in ANSWER})
    return out


def _revisions(c, map_id: str) -> list[dict]:
    r = c.get(f"/v1/maps/{map_id}/revisions", headers=ADMIN)
    assert r.status_code == 200, r.text
    return r.json()


def _problem(r, status: int, kind: str) -> dict:
    assert r.status_code == status, r.text
    assert r.headers["content-type"] == PROBLEM
    assert r.json()["type"] == f"urn:vloc:problem:{kind}"
    return r.json()


def test_a_map_restored_to_an_earlier_revision_answers_as_it_did(module_client, shots):
    c = module_client
    images, queries = shots[0], shots[1][2:5]
    map_id = c.post("/v1/maps", json={"name": "revisions"}, headers=ADMIN).json()["id"]
    assert _revisions(c, map_id) == []
    c.post(f"/v1/maps/{map_id}/images", files=jpeg_files(images[:7]), headers=ADMIN)
    first_job = _build(c, map_id)
    first = _answers(c, map_id, queries)
    assert {a["map_revision"] for a in first} == {1}

    c.post(f"/v1/maps/{map_id}/images", files=jpeg_files(images[7:]), headers=ADMIN)
    _build(c, map_id)
    second = _answers(c, map_id, queries)
    assert {a["map_revision"] for a in second} == {2}
    listed = _revisions(c, map_id)
    assert [(r["revision"], r["current"], r["base_revision"], r["image_count"], r["added"],
             r["removed"]) for r in listed] == [(2, True, 1, 10, 3, 0), (1, False, 0, 7, 7, 0)]
    assert listed[1]["job_id"] == first_job["id"]
    assert all(r["disk_bytes"] > 0 and r["active_sessions"] == 0 for r in listed)
    # three images of ten new to the vocabularies: revision 2 trained its own
    assert [r["vocabularies_from"] for r in listed] == [2, 1]
    assert listed[0]["geometry"] == c.get(f"/v1/maps/{map_id}", headers=ADMIN).json()[
        "geometry"]
    _assert_shares_the_first_images_files(c, map_id, listed, first=7)

    # a session that does not follow the map keeps revision 2 through the restore
    r = c.post("/v1/sessions", json={"map_id": map_id, "mode": "hybrid", "params": FAST,
                                     "seed": 1, "follow_map": False}, headers=ADMIN)
    session = r.json()["id"]
    assert (r.json()["map_revision"], r.json()["follows_map"]) == (2, False)
    assert [x["active_sessions"] for x in _revisions(c, map_id)] == [1, 0]

    r = c.post(f"/v1/maps/{map_id}/revisions/1/restore", headers=ADMIN)
    assert r.status_code == 200, r.text
    restored = r.json()
    assert (restored["revision"], restored["status"], restored["pending_images"]) == (
        1, "unbuilt", 3)
    assert [x["current"] for x in _revisions(c, map_id)] == [False, True]
    # exactly the answers revision 1 gave, in its frame
    assert _answers(c, map_id, queries) == first
    held = {i["filename"]: i for i in c.get(f"/v1/maps/{map_id}/images",
                                            headers=ADMIN).json()}
    assert {n for n, i in held.items() if i["built_revision"] is None} == {
        s.name for s in images[7:]}
    assert all(i["east"] is not None for n, i in held.items() if i["built_revision"] == 1)
    assert c.get(f"/v1/sessions/{session}", headers=ADMIN).json()["map_revision"] == 2

    # revision 2 is in use; revision 1 is current: neither can go, and nothing changes
    before = snapshot(c)
    p = _problem(c.delete(f"/v1/maps/{map_id}/revisions/2", headers=ADMIN), 409,
                 "revision-in-use")
    assert p["sessions"] == 1
    _problem(c.delete(f"/v1/maps/{map_id}/revisions/1", headers=ADMIN), 409,
             "revision-current")
    _problem(c.post(f"/v1/maps/{map_id}/revisions/7/restore", headers=ADMIN), 404,
             "not-found")
    _problem(c.delete(f"/v1/maps/{UNKNOWN_ID}/revisions/1", headers=ADMIN), 404, "not-found")
    assert c.post(f"/v1/maps/{map_id}/revisions/0/restore", headers=ADMIN).status_code == 422
    assert snapshot(c) == before

    assert c.delete(f"/v1/sessions/{session}", headers=ADMIN).status_code == 204
    assert c.delete(f"/v1/maps/{map_id}/revisions/2", headers=ADMIN).status_code == 204
    listed = _revisions(c, map_id)
    assert [(x["revision"], x["dropped_at"] is not None, x["disk_bytes"]) for x in listed][0] \
        == (2, True, None)
    assert listed[1]["dropped_at"] is None
    assert not c.app.state.ctx.settings.packed_map_dir(map_id, 2).exists()
    # revision 1 lost none of the files it shared with revision 2
    assert listed[1]["shared_bytes"] == 0
    assert _answers(c, map_id, queries) == first
    # dropping it again changes nothing; restoring it cannot be
    assert c.delete(f"/v1/maps/{map_id}/revisions/2", headers=ADMIN).status_code == 204
    _problem(c.post(f"/v1/maps/{map_id}/revisions/2/restore", headers=ADMIN), 404,
             "not-found")

    # the next build packs a revision after every one the map has had; of the same images
    # as revision 2, it takes up the COLMAP models that build kept, aligned to the GPS
    # again (the order COLMAP's model lists its images in, read back from disk, moves the
    # alignment's sums in their last bits), and answers as revision 2 did
    _build(c, map_id)
    latest = _revisions(c, map_id)[0]
    assert (latest["revision"], latest["base_revision"], latest["added"]) == (3, 1, 3)
    third = _answers(c, map_id, queries)
    assert len(third) == len(second)
    for got, want in zip(third, second, strict=True):
        _assert_same_answer(got, want | {"map_revision": 3})


def _assert_shares_the_first_images_files(c, map_id: str, listed: list[dict], *,
                                          first: int) -> None:
    """Revision 2, ``first`` images of revision 1 and more after them, holds the SIFT and ORB
    features of each chunk of those images in revision 1's very files; each revision counts
    them as shared."""
    folders = [c.app.state.ctx.settings.packed_map_dir(map_id, r) for r in (1, 2)]
    meta = [json.loads((f / "meta.json").read_text()) for f in folders]
    bounds = chunk_bounds(meta[1]["names"], every=2)
    assert meta[1]["names"][:first] == meta[0]["names"]
    old = sum(stop <= first for stop in bounds[1:])
    assert old >= 1
    linked = 0
    for stem in ("sift_keypoints", "sift_descriptors", "orb_keypoints", "orb_descriptors",
                 "global_wgoh"):
        chunks = [[name for name, _ in m["chunks"][stem]] for m in meta]
        assert chunks[1][:old] == chunks[0][:old]
        for name in chunks[1][:old]:
            assert os.path.samefile(folders[0] / name, folders[1] / name)
            linked += (folders[1] / name).stat().st_size
        assert not set(chunks[1][old:]) & set(chunks[0])
    for r in listed:
        assert linked <= r["shared_bytes"] < r["disk_bytes"]


def _assert_same_answer(got: dict, want: dict) -> None:
    """The same answer, its numbers to within a micrometre (1e-10 degrees) and their
    round-off."""
    assert got.keys() == want.keys()
    for key, value in want.items():
        if key in ("lat", "lon"):
            assert got[key] == pytest.approx(value, abs=1e-10), key
        elif key == "cov" or isinstance(value, float):
            assert got[key] == pytest.approx(value, abs=1e-5), key
        else:
            assert got[key] == value, key


def test_restoring_waits_for_a_running_build(module_client, shots, hold_worker):
    c = module_client
    map_id = c.post("/v1/maps", json={"name": "busy"}, headers=ADMIN).json()["id"]
    c.post(f"/v1/maps/{map_id}/images", files=jpeg_files(shots[0][:5]), headers=ADMIN)
    _build(c, map_id)
    c.post(f"/v1/maps/{map_id}/images", files=jpeg_files(shots[0][5:7]), headers=ADMIN)
    hold_worker()
    job = c.post(f"/v1/maps/{map_id}/build", headers=ADMIN).json()["job_id"]
    _problem(c.post(f"/v1/maps/{map_id}/revisions/1/restore", headers=ADMIN), 409, "map-busy")
    assert c.get(f"/v1/jobs/{job}", headers=ADMIN).json()["status"] in ("queued", "running")


@pytest.mark.parametrize("path", ["revisions", "revisions/1/restore"])
def test_revisions_need_the_admin_key(module_client, path):
    method = "get" if path == "revisions" else "post"
    r = getattr(module_client, method)(f"/v1/maps/{UNKNOWN_ID}/{path}")
    assert r.status_code == 401


def _session(c, map_id: str, **extra) -> tuple[str, dict]:
    r = c.post("/v1/sessions", json={"map_id": map_id, "mode": "hybrid", "params": FAST,
                                     "seed": 2, **extra}, headers=ADMIN)
    assert r.status_code == 201, r.text
    return r.json()["id"], {"Authorization": f"Bearer {r.json()['token']}"}


def _localise(c, sid: str, auth: dict, shot) -> dict:
    r = c.post(f"/v1/sessions/{sid}/frames", content=shot.jpeg, params={"wait": "true"},
               headers={**auth, "Content-Type": "image/jpeg"})
    assert r.status_code == 200 and r.json()["type"] == "pose", r.text
    return r.json()


def test_sessions_follow_their_map_to_each_new_revision_and_pinned_ones_stay(module_client,
                                                                            shots):
    """A session follows its map by default: restored to revision 1, then built again as
    revision 3, the map takes the session along between two frames, with its filter's
    state, no frame lost, each pose naming the revision it was made on. A session that
    pinned revision 1 and one that chose not to follow stay where they started."""
    c = module_client
    images, queries = shots[0], shots[1]
    map_id = c.post("/v1/maps", json={"name": "followed"}, headers=ADMIN).json()["id"]
    c.post(f"/v1/maps/{map_id}/images", files=jpeg_files(images[:7]), headers=ADMIN)
    _build(c, map_id)
    c.post(f"/v1/maps/{map_id}/images", files=jpeg_files(images[7:]), headers=ADMIN)
    _build(c, map_id)

    follows, f_auth = _session(c, map_id)
    pinned, p_auth = _session(c, map_id, map_revision=1)
    stays, s_auth = _session(c, map_id, follow_map=False)
    read = {sid: c.get(f"/v1/sessions/{sid}", headers=ADMIN).json()
            for sid in (follows, pinned, stays)}
    assert [(read[s]["map_revision"], read[s]["follows_map"])
            for s in (follows, pinned, stays)] == [(2, True), (1, False), (2, False)]

    def walk(frames) -> list[dict]:
        return [_localise(c, sid, auth, q) for q in frames
                for sid, auth in ((follows, f_auth), (pinned, p_auth), (stays, s_auth))]

    before = walk(queries[:3])
    assert [p["map_revision"] for p in before] == [2, 1, 2] * 3
    assert c.post(f"/v1/maps/{map_id}/revisions/1/restore", headers=ADMIN).status_code == 200
    after = walk(queries[3:6])
    assert [p["map_revision"] for p in after] == [1, 1, 2] * 3
    assert _build(c, map_id)["revision"] == 3
    last = walk(queries[6:9])
    assert [p["map_revision"] for p in last] == [3, 1, 2] * 3

    stored = c.get(f"/v1/sessions/{follows}/poses", headers=f_auth).json()
    assert [(p["seq"], p["map_revision"]) for p in stored] == [
        (i, r) for i, r in enumerate([2] * 3 + [1] * 3 + [3] * 3)]
    got = c.get(f"/v1/sessions/{follows}", headers=ADMIN).json()
    assert (got["map_revision"], got["follows_map"], got["frames_processed"],
            got["frames_failed"]) == (3, True, 9, 0)
    assert c.get(f"/v1/sessions/{pinned}", headers=ADMIN).json()["map_revision"] == 1
    # the filter kept its belief across the moves: it tracks the true positions in each
    # revision's frame as well as the sessions that never moved
    def error(p, shot) -> float:
        return float(np.hypot((p["lat"] - shot.lat) * 111_320.0,
                              (p["lon"] - shot.lon) * 111_320.0 * np.cos(np.radians(shot.lat))))

    moved = [error(p, q) for p, q in zip(after[0::3] + last[0::3], queries[3:9], strict=True)]
    fixed = [error(p, q) for p, q in zip(after[2::3] + last[2::3], queries[3:9], strict=True)]
    assert max(moved) <= max(fixed) + 5.0, (moved, fixed)
    # revision 2 is no longer used by an active session that follows; the one that stays
    # holds it
    assert [x["active_sessions"] for x in _revisions(c, map_id)] == [1, 1, 1]
    metrics = c.get("/metrics", headers=ADMIN).text
    assert 'vloc_session_moves_total{outcome="moved"} 2.0' in metrics


def test_a_pinned_revision_must_exist_and_a_pinned_session_cannot_follow(module_client,
                                                                        shots):
    c = module_client
    images = shots[0]
    map_id = c.post("/v1/maps", json={"name": "pinned"}, headers=ADMIN).json()["id"]
    c.post(f"/v1/maps/{map_id}/images", files=jpeg_files(images[:6]), headers=ADMIN)
    _build(c, map_id)
    before = snapshot(c)
    _problem(c.post("/v1/sessions", json={"map_id": map_id, "map_revision": 4},
                    headers=ADMIN), 404, "not-found")
    p = _problem(c.post("/v1/sessions", json={"map_id": map_id, "map_revision": 1,
                                              "follow_map": True}, headers=ADMIN),
                 422, "bad-params")
    assert "follow_map" in p["detail"]
    assert c.post("/v1/sessions", json={"map_id": map_id, "map_revision": 0},
                  headers=ADMIN).status_code == 422
    assert snapshot(c) == before
