"""Images whose pixel data is incomplete are refused, as map images and as frames: half a
JPEG with an end marker appended (libjpeg would fill the missing half with grey), and a
JPEG whose header claims far more pixels than its data holds."""

from __future__ import annotations

import struct

import pytest

from tests.app.conftest import ADMIN, snapshot
from tests.app.test_sessions import post_frame
from vloc.workers.core.image import ImageError, decode_image


def half_with_end_marker(jpeg: bytes) -> bytes:
    return jpeg[: len(jpeg) // 2] + b"\xff\xd9"


def claiming(jpeg: bytes, width: int, height: int) -> bytes:
    """The JPEG with its frame header (SOF) saying ``width`` x ``height``."""
    i = 2
    while True:
        marker, length = jpeg[i + 1], struct.unpack(">H", jpeg[i + 2:i + 4])[0]
        if marker in (0xC0, 0xC1, 0xC2):
            at = i + 5
            return jpeg[:at] + struct.pack(">HH", height, width) + jpeg[at + 4:]
        i += 2 + length


def test_the_decoder_refuses_incomplete_jpegs(shots):
    good = shots[1][0].jpeg
    assert decode_image(good).ndim == 3
    for bad in (half_with_end_marker(good), claiming(good, 1024, 20000)):
        with pytest.raises(ImageError, match="incomplete"):
            decode_image(bad)


@pytest.mark.parametrize("make", [half_with_end_marker, lambda j: claiming(j, 1024, 1500)],
                         ids=["half", "tall-header"])
def test_an_incomplete_map_image_is_refused_and_nothing_stored(service, shots, make):
    c = service.client
    before = snapshot(c)
    bad = make(shots[0][3].jpeg)
    r = c.post(f"/v1/maps/{service.map_id}/images", headers=ADMIN,
               files=[("files", ("cut.jpg", bad, "image/jpeg"))])
    assert r.status_code == 422, r.text
    assert r.json()["rejected"][0]["status"] == 422
    assert "incomplete" in r.json()["rejected"][0]["detail"]
    assert snapshot(c) == before


@pytest.mark.parametrize("make", [half_with_end_marker, lambda j: claiming(j, 1024, 1500)],
                         ids=["half", "tall-header"])
def test_an_incomplete_frame_gives_no_estimate(service, shots, make):
    c = service.client
    sid, auth = service.new_session()
    r = post_frame(c, sid, make(shots[1][0].jpeg), auth, wait="true")
    assert r.status_code == 422, r.text
    assert r.json()["type"].endswith("frame-bad-image") and "incomplete" in r.json()["detail"]
    read = c.get(f"/v1/sessions/{sid}", headers=auth).json()
    assert (read["frames_processed"], read["frames_failed"], read["last_pose"]) == (0, 1, None)
    # the session goes on with the next good frame
    assert post_frame(c, sid, shots[1][1].jpeg, auth, wait="true").status_code == 200
