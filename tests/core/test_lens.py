"""Focal length in pixels from the EXIF of real JPEG files."""

from __future__ import annotations

import io

import pytest
from PIL import ExifTags, Image
from PIL.TiffImagePlugin import IFDRational

from vloc.workers.core.lens import read_focal_px
from vloc.workers.core.mapbuild import typical_focal_px

B = ExifTags.Base

# Canon PowerShot ELPH 300 HS: a 4.3 mm lens and 16393.44 sensor pixels per inch
# (645.41 per mm) at 4000 px across: 4.3 * 645.41 = 2775.3 px at 4000 px, 222.0 px at 320.
CANON = {B.FocalLength: IFDRational(43, 10),
         B.FocalPlaneXResolution: IFDRational(4000000, 244),
         B.FocalPlaneResolutionUnit: 2, B.ExifImageWidth: 4000}
CANON_F320 = 4.3 * (4000000 / 244 / 25.4) * 320 / 4000


def _jpeg(tags: dict | None, size=(64, 48)) -> bytes:
    buf = io.BytesIO()
    im = Image.new("RGB", size, (90, 120, 60))
    if tags is None:
        im.save(buf, "JPEG")
    else:
        exif = Image.Exif()
        exif[B.Make] = "Canon"
        ifd = exif.get_ifd(ExifTags.IFD.Exif)
        ifd.update(tags)
        im.save(buf, "JPEG", exif=exif)
    return buf.getvalue()


def test_canon_elph_300_hs():
    assert read_focal_px(_jpeg(CANON), 320) == pytest.approx(222.02, abs=0.01)
    assert read_focal_px(_jpeg(CANON), 320) == pytest.approx(CANON_F320, rel=1e-9)
    # proportional to the working width
    assert read_focal_px(_jpeg(CANON), 640) == pytest.approx(2 * CANON_F320, rel=1e-9)


@pytest.mark.parametrize(("unit", "res"), [(3, 16393.44 / 2.54), (4, 645.41), (5, 0.64541)])
def test_focal_plane_resolution_units(unit, res):
    # per centimetre, per millimetre, per micrometre: the same sensor
    tags = {**CANON, B.FocalPlaneXResolution: res, B.FocalPlaneResolutionUnit: unit}
    assert read_focal_px(_jpeg(tags), 320) == pytest.approx(222.0, abs=0.05)


def test_missing_unit_means_inches():
    tags = {k: v for k, v in CANON.items() if k != B.FocalPlaneResolutionUnit}
    assert read_focal_px(_jpeg(tags), 320) == pytest.approx(CANON_F320, rel=1e-9)


def test_missing_exif_width_uses_the_image_width():
    # Without ExifImageWidth the resolution refers to the file's own 64 px: a coarse
    # 10.32 px/mm sensor, 4.3 * 10.32 = 44.4 px at 64 px across, 221.9 px at 320.
    tags = {B.FocalLength: 4.3, B.FocalPlaneXResolution: 10.32, B.FocalPlaneResolutionUnit: 4}
    assert read_focal_px(_jpeg(tags), 320) == pytest.approx(4.3 * 10.32 * 320 / 64)


def test_35mm_equivalent_only():
    # 28 mm on a 36 mm wide frame: 28 / 36 of the width.
    f = read_focal_px(_jpeg({B.FocalLengthIn35mmFilm: 28}), 320)
    assert f == pytest.approx(28 * 320 / 36.0)
    assert f == pytest.approx(248.89, abs=0.01)


def test_35mm_equivalent_when_the_focal_plane_says_nothing_useful():
    # an unknown resolution unit (1: none), or a focal length that is not plausible
    tags = {**CANON, B.FocalPlaneResolutionUnit: 1, B.FocalLengthIn35mmFilm: 24}
    assert read_focal_px(_jpeg(tags), 320) == pytest.approx(24 * 320 / 36.0)
    tags = {**CANON, B.FocalLength: 0, B.FocalLengthIn35mmFilm: 24}
    assert read_focal_px(_jpeg(tags), 320) == pytest.approx(24 * 320 / 36.0)
    tags = {**CANON, B.FocalLength: 1000.0, B.FocalLengthIn35mmFilm: 24}
    assert read_focal_px(_jpeg(tags), 320) == pytest.approx(24 * 320 / 36.0)


@pytest.mark.parametrize("data", [
    _jpeg(None),  # no EXIF at all
    _jpeg({}),  # EXIF without lens tags
    _jpeg({B.FocalLength: IFDRational(43, 10)}),  # a focal length, nothing to scale it
    _jpeg({**CANON, B.FocalPlaneResolutionUnit: 1}),  # unknown unit, no 35 mm figure
    _jpeg({B.FocalLengthIn35mmFilm: 0}),
    b"",
    b"not an image at all",
    b"\xff\xd8\xff\xe1\x00\x10Exif\x00\x00garbage-garbage",
])
def test_no_usable_lens_is_none(data):
    assert read_focal_px(data, 320) is None


def test_typical_focal_px_is_the_median():
    files = [_jpeg({B.FocalLengthIn35mmFilm: f}) for f in (24, 28, 35)]
    assert typical_focal_px(files) == pytest.approx(28 * 320 / 36.0)
    # files without a lens are skipped; callables are read
    files += [_jpeg(None), b"junk"]
    assert typical_focal_px([lambda d=d: d for d in files]) == pytest.approx(28 * 320 / 36.0)
    assert typical_focal_px([_jpeg({B.FocalLengthIn35mmFilm: f}) for f in (24, 35)]) \
        == pytest.approx((24 + 35) / 2 * 320 / 36.0)
    assert typical_focal_px([_jpeg({B.FocalLengthIn35mmFilm: 28})], 640) \
        == pytest.approx(28 * 640 / 36.0)


def test_typical_focal_px_without_lenses_is_none():
    assert typical_focal_px([]) is None
    assert typical_focal_px([_jpeg(None), b"junk"]) is None


def test_typical_focal_px_reads_a_sample():
    canon = _jpeg(CANON)
    read = []

    def opener(i):
        def read_bytes():
            read.append(i)
            return canon
        return read_bytes

    assert typical_focal_px([opener(i) for i in range(100)], sample=25) \
        == pytest.approx(CANON_F320)
    assert read == list(range(0, 100, 4))
