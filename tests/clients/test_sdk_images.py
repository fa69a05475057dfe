"""Every SDK call that takes an image takes it in each documented form: a path (``Path`` or
``str``), the bytes, or ``(name, bytes)``; the blocking client in process, the async client
and the async stream over real sockets."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.clients.conftest import ADMIN_KEY, FAST
from vloc.clients.sdk import AsyncClient, Localization, Pose

FORMS = ("path", "str", "bytes", "pair")


def _as(form: str, jpeg: bytes, folder: Path, name: str):
    """One JPEG in the named form (written to ``folder`` for the path forms)."""
    path = folder / name
    path.write_bytes(jpeg)
    return {"path": path, "str": str(path), "bytes": jpeg, "pair": (name, jpeg)}[form]


@pytest.mark.parametrize("form", FORMS)
def test_upload_images(vloc, shots, tmp_path, form):
    maps, _ = shots
    m = vloc.create_map(f"upload {form}")
    done = vloc.upload_images(m.id, [_as(form, maps[0].jpeg, tmp_path, maps[0].name)])
    assert len(done.accepted) == 1 and done.rejected == []
    assert done.accepted[0].filename == (maps[0].name if form != "bytes" else "image-0")
    vloc.delete_map(m.id)


@pytest.mark.parametrize("form", FORMS)
def test_send_frame_and_localize(vloc, built_map, shots, tmp_path, form):
    _, queries = shots
    image = _as(form, queries[0].jpeg, tmp_path, "frame.jpg")
    s = vloc.create_session(built_map, params=FAST, seed=1)
    try:
        assert isinstance(vloc.send_frame(s, image, seq=0, wait=True), Pose)
    finally:
        vloc.delete_session(s)
    assert isinstance(vloc.localize(built_map, image, seed=1), Localization)


@pytest.mark.parametrize("form", FORMS)
def test_stream_send_frame(vloc, built_map, shots, tmp_path, form):
    _, queries = shots
    s = vloc.create_session(built_map, params=FAST, seed=1)
    try:
        with vloc.stream(s, timeout=60) as poses:
            poses.send_frame(_as(form, queries[0].jpeg, tmp_path, "frame.jpg"), seq=0)
            got = poses.receive()
    finally:
        vloc.delete_session(s)
    assert isinstance(got, Pose) and got.seq == 0


def test_an_image_of_another_type_is_refused_before_sending(vloc, built_map):
    with pytest.raises(TypeError, match="path, bytes or"):
        vloc.localize(built_map, 12)


@pytest.mark.anyio
async def test_async_calls_and_stream(live_server, shots, tmp_path):
    maps, queries = shots
    async with AsyncClient(live_server, admin_key=ADMIN_KEY) as vloc:
        m = await vloc.create_map("async image forms")
        up = await vloc.upload_images(m.id, [_as(form, s.jpeg, tmp_path, s.name)
                                             for form, s in zip(FORMS, maps, strict=False)]
                                      + [(s.name, s.jpeg) for s in maps[len(FORMS):]])
        assert len(up.accepted) == len(maps)
        await vloc.wait_for_job((await vloc.build_map(m.id)).id, timeout=120,
                                poll_interval=0.1)
        s = await vloc.create_session(m.id, params=FAST, seed=1)
        async with await vloc.stream(s, timeout=60) as poses:
            for i, form in enumerate(FORMS):
                image = _as(form, queries[i].jpeg, tmp_path, f"q{i}.jpg")
                await vloc.send_frame(s, image, seq=2 * i)
                await poses.send_frame(image, seq=2 * i + 1)
                assert isinstance(await vloc.localize(m.id, image, seed=1), Localization)
            got = [await poses.receive() for _ in range(2 * len(FORMS))]
        assert [p.seq for p in got] == list(range(2 * len(FORMS)))
        assert all(isinstance(p, Pose) for p in got)
        await vloc.delete_session(s)
