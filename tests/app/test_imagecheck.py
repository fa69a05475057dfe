"""Header checks of uploads in the API process."""

from __future__ import annotations

from io import BytesIO

import pytest
from PIL import Image

from tests.app.imagery import plain_jpeg, png, png_bomb
from vloc.app.imagecheck import check_image, kind_of_content_type, sniff
from vloc.app.problems import Problem


def test_sniff_and_content_types():
    assert sniff(plain_jpeg()) == "jpeg" and sniff(png()) == "png" and sniff(b"GIF89a") is None
    assert kind_of_content_type("image/jpeg; charset=binary") == "jpeg"
    assert kind_of_content_type("IMAGE/PNG") == "png"
    assert kind_of_content_type("image/gif") is None and kind_of_content_type(None) is None


def test_good_images_give_their_size():
    h = check_image(plain_jpeg(size=(64, 48)), max_pixels=10_000)
    assert (h.kind, h.width, h.height, h.content_type, h.suffix) == (
        "jpeg", 64, 48, "image/jpeg", ".jpg")
    assert check_image(png(size=(30, 20)), max_pixels=600, declared="png").width == 30


def test_a_jpegs_orientation_is_read_with_its_size_and_handed_to_the_decode():
    """The worker decodes a frame from the header checked here (it does not read it
    again): the EXIF orientation goes with the size, and the decode applies it."""
    import cv2
    import numpy as np

    from vloc.workers.core.image import Header, decode_image

    plain = plain_jpeg(size=(64, 48))
    exif = Image.Exif()
    exif[0x0112] = 6  # stored sideways: seen turned 90 degrees clockwise
    with Image.open(BytesIO(plain)) as im:
        out = BytesIO()
        im.save(out, "JPEG", exif=exif.tobytes())
    turned = out.getvalue()
    assert check_image(plain, max_pixels=10**6).core == Header(64, 48, 1)
    header = check_image(turned, max_pixels=10**6)
    assert header.core == Header(64, 48, 6)
    assert png() and check_image(png(size=(30, 20)), max_pixels=600).orientation == 1
    decoded = decode_image(turned, header=header.core)
    assert decoded.shape[:2] == (64, 48)
    np.testing.assert_array_equal(decoded, cv2.imdecode(np.frombuffer(turned, np.uint8),
                                                        cv2.IMREAD_COLOR))


@pytest.mark.parametrize(("data", "declared", "max_pixels", "status", "kind"), [
    (b"", None, 10**6, 422, "empty-image"),
    (b"hello", None, 10**6, 422, "bad-image"),
    (plain_jpeg()[:200], None, 10**6, 422, "truncated-image"),
    (plain_jpeg()[:-300], None, 10**6, 422, "truncated-image"),
    (png()[:-12], None, 10**6, 422, "truncated-image"),
    (png(), "jpeg", 10**6, 415, "content-type-mismatch"),
    (plain_jpeg(size=(64, 48)), None, 64 * 48 - 1, 413, "too-many-pixels"),
    (png_bomb(), None, 10**6, 413, "too-many-pixels"),
    (b"\xff\xd8\xff" + b"\x00" * 50, None, 10**6, 422, "bad-image"),
])
def test_bad_images(data, declared, max_pixels, status, kind):
    with pytest.raises(Problem) as info:
        check_image(data, max_pixels=max_pixels, declared=declared)
    assert (info.value.status, info.value.kind) == (status, kind)


def test_unidentifiable_image_detail_names_no_python_object():
    """Pillow names the file object it was given; the detail must not show it."""
    from vloc.app.imagecheck import check_image
    from vloc.app.problems import Problem

    with pytest.raises(Problem) as info:
        check_image(b"\xff\xd8\xff" + bytes(200), max_pixels=10**6)
    assert info.value.status == 422 and "object at 0x" not in info.value.detail
    assert "BytesIO" not in info.value.detail
