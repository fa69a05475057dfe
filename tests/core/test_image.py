"""A JPEG is decoded once, strictly, and to the pixels OpenCV gives: checked against OpenCV's
own decode (the reference the map and every estimate were made with) over the kinds of JPEG
cameras write, and on the real surveys where they are present."""

from __future__ import annotations

from io import BytesIO

import cv2
import numpy as np
import pytest
from PIL import Image

from vloc.workers.core import image
from vloc.workers.core.image import WORK_SIZE, ImageError, decode_image, load_frame


def _reference(data: bytes, min_size=WORK_SIZE) -> np.ndarray:
    """OpenCV's decode at the scale the working size allows: the pixels every JPEG was
    decoded to before."""
    with Image.open(BytesIO(data)) as im:
        width, height = im.size
    flag = cv2.IMREAD_COLOR
    for factor, reduced in image._REDUCED if min_size is not None else ():
        if width // factor >= min_size[0] and height // factor >= min_size[1]:
            flag = reduced
            break
    return cv2.imdecode(np.frombuffer(data, np.uint8), flag)


def _texture(width: int, height: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    noise = rng.integers(0, 256, (height, width, 3), np.uint8)
    return cv2.GaussianBlur(noise, (7, 7), 2.0)


def _jpegs():
    """JPEGs of the kinds cameras write: qualities, odd sizes, grey, progressive, chroma
    subsampled or not, restart markers."""
    for k, (width, height) in enumerate([(320, 240), (333, 251), (640, 480), (1024, 768),
                                          (1500, 1001), (2000, 1500)]):
        colour = _texture(width, height, k)
        for quality in (40, 92):
            yield f"{width}x{height} q{quality}", cv2.imencode(
                ".jpg", colour, [cv2.IMWRITE_JPEG_QUALITY, quality])[1].tobytes()
        yield f"{width}x{height} grey", cv2.imencode(
            ".jpg", cv2.cvtColor(colour, cv2.COLOR_BGR2GRAY))[1].tobytes()
        yield f"{width}x{height} progressive", cv2.imencode(
            ".jpg", colour, [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])[1].tobytes()
        yield f"{width}x{height} 4:4:4", cv2.imencode(
            ".jpg", colour, [cv2.IMWRITE_JPEG_SAMPLING_FACTOR,
                             cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444])[1].tobytes()
        yield f"{width}x{height} restarts", cv2.imencode(
            ".jpg", colour, [cv2.IMWRITE_JPEG_RST_INTERVAL, 4])[1].tobytes()


@pytest.mark.parametrize(("name", "data"), list(_jpegs()), ids=lambda v: v
                         if isinstance(v, str) else "")
def test_one_strict_decode_gives_opencvs_pixels(name, data, monkeypatch):
    want = _reference(data)
    full = _reference(data, min_size=None)
    # decoded once: OpenCV's decoder is not called
    monkeypatch.setattr(image.cv2, "imdecode", lambda *a: pytest.fail("decoded twice"))
    np.testing.assert_array_equal(decode_image(data, min_size=WORK_SIZE), want)
    np.testing.assert_array_equal(decode_image(data), full)


def _with_orientation(data: bytes, orientation: int) -> bytes:
    exif = Image.Exif()
    exif[0x0112] = orientation
    with Image.open(BytesIO(data)) as im:
        out = BytesIO()
        im.save(out, "JPEG", quality=90, exif=exif.tobytes())
    return out.getvalue()


@pytest.mark.parametrize("orientation", [1, 3, 6, 8])
def test_an_exif_orientation_is_applied_as_opencv_applies_it(orientation):
    plain = cv2.imencode(".jpg", _texture(400, 300, 9))[1].tobytes()
    data = _with_orientation(plain, orientation)
    got = decode_image(data, min_size=(100, 100))
    np.testing.assert_array_equal(got, _reference(data, min_size=(100, 100)))
    assert got.shape[:2] == ((150, 200) if orientation in (1, 3) else (200, 150))


def test_a_jpeg_cut_short_is_refused_however_it_ends():
    data = cv2.imencode(".jpg", _texture(640, 480, 3))[1].tobytes()
    cut = data[: len(data) // 2]
    with pytest.raises(ImageError, match="truncated"):
        decode_image(cut)
    with pytest.raises(ImageError, match="corrupt or incomplete JPEG"):
        decode_image(cut + b"\xff\xd9")  # an end marker appended: still half a file
    with pytest.raises(ImageError, match="frame header says"):
        decode_image(data, header=image.Header(641, 480))


def test_survey_images_decode_as_before(seneca_dir):
    files = sorted(seneca_dir.rglob("*.jpg"))[::10]
    assert files
    for path in files:
        data = path.read_bytes()
        want = _reference(data)
        frame = load_frame(data)
        np.testing.assert_array_equal(decode_image(data, min_size=WORK_SIZE), want)
        assert frame.grey.shape == (WORK_SIZE[1], WORK_SIZE[0])
