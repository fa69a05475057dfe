"""EXIF GPS read/write: round trips, known rationals, lossless splicing, malformed tags."""

from __future__ import annotations

import csv
import io
import math
from datetime import UTC, datetime, timedelta, timezone

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import ExifTags, Image
from PIL.TiffImagePlugin import IFDRational as R

from vloc.workers.core.exif import GpsError, GpsTag, encode_jpeg_with_gps, read_gps, write_gps
from vloc.workers.core.geo import GeoOrigin
from vloc.workers.core.image import ImageError, decode_image


def _image(seed: int = 0, shape=(48, 64, 3)) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, shape, dtype=np.uint8)


def _jpeg(image: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 85])
    assert ok
    return buf.tobytes()


def _pillow_jpeg(exif: Image.Exif, fmt: str = "JPEG") -> bytes:
    buf = io.BytesIO()
    Image.new("RGB", (16, 8), (40, 90, 200)).save(buf, fmt, exif=exif.tobytes())
    return buf.getvalue()


def _ground_error_m(tag: GpsTag, lat: float, lon: float) -> float:
    east, north = GeoOrigin(lat, lon).to_local(tag.lat, tag.lon)
    return float(math.hypot(east, north))


def _scan_data(jpeg: bytes) -> bytes:
    """The bytes from the first SOS marker on: the compressed pixels."""
    return jpeg[jpeg.index(b"\xff\xda"):]


@pytest.mark.parametrize(("lat", "lon", "alt"), [
    (41.0346708, -83.3057253, 281.69),   # north-west (seneca-uav)
    (-33.8567844, 151.2152967, 58.1),    # south-east
    (-54.8019121, -68.3029511, -3.25),   # south-west, below sea level
    (51.5007292, 0.0000012, 0.0),        # just east of Greenwich
    (0.0, -0.0000009, None),             # equator, just west of Greenwich, no altitude
    (89.9999999, 179.9999999, 8848.86),
    (-89.9999999, -179.9999999, -430.5),
])
def test_round_trip_within_one_centimetre(lat, lon, alt):
    tag = read_gps(encode_jpeg_with_gps(_image(), lat=lat, lon=lon, alt=alt))
    assert tag is not None
    assert _ground_error_m(tag, lat, lon) < 0.01
    assert abs(tag.lat - lat) < 1e-9 and abs(tag.lon - lon) < 1e-9
    assert math.copysign(1, tag.lon) == math.copysign(1, lon) or abs(lon) < 1e-9
    if alt is None:
        assert tag.alt is None
    else:
        assert tag.alt == pytest.approx(alt, abs=0.0005)


@settings(max_examples=60, deadline=None)
@given(lat=st.floats(-89.99, 89.99), lon=st.floats(-180, 180),
       alt=st.floats(-500, 9000))
def test_round_trip_property(lat, lon, alt):
    jpeg = _jpeg(_image(1, (8, 8, 3)))
    tag = read_gps(write_gps(jpeg, lat=lat, lon=lon, alt=alt))
    assert _ground_error_m(tag, lat, lon) < 0.01
    assert tag.alt == pytest.approx(alt, abs=0.0005)


def test_written_rationals_match_hand_computed_dms():
    # 41.0346708 deg = 41 deg + 0.0346708 * 60 = 2.080248 min -> 2 min + 0.080248 * 60 s
    # = 4.81488 s; 83.3057253 deg -> 18.343518 min -> 20.61108 s, west.
    jpeg = write_gps(_jpeg(_image()), lat=41.0346708, lon=-83.3057253, alt=-2.5)
    gps = Image.open(io.BytesIO(jpeg)).getexif().get_ifd(ExifTags.IFD.GPSInfo)
    assert gps[ExifTags.GPS.GPSLatitudeRef] == "N"
    assert gps[ExifTags.GPS.GPSLongitudeRef] == "W"
    lat_dms = [(r.numerator, r.denominator) for r in gps[ExifTags.GPS.GPSLatitude]]
    assert lat_dms[:2] == [(41, 1), (2, 1)] and lat_dms[2][0] / lat_dms[2][1] == 4.81488
    lon_dms = [float(r) for r in gps[ExifTags.GPS.GPSLongitude]]
    assert lon_dms == [83.0, 18.0, 20.61108]
    assert gps[ExifTags.GPS.GPSAltitudeRef] in (1, b"\x01")
    assert float(gps[ExifTags.GPS.GPSAltitude]) == 2.5


def test_write_keeps_pixels_and_compressed_data():
    original = _jpeg(_image(2, (120, 160, 3)))
    tagged = write_gps(original, lat=10.5, lon=-20.25, alt=5.0,
                       captured_at=datetime(2021, 5, 6, 7, 8, 9))
    assert _scan_data(tagged) == _scan_data(original)
    np.testing.assert_array_equal(decode_image(tagged), decode_image(original))
    # Writing again replaces the EXIF block instead of adding a second one.
    again = write_gps(tagged, lat=-1.0, lon=2.0)
    assert again.count(b"Exif\x00\x00") == 1
    assert _scan_data(again) == _scan_data(original)
    assert read_gps(again) == GpsTag(lat=-1.0, lon=2.0, alt=None,
                                     captured_at=datetime(2021, 5, 6, 7, 8, 9))


def test_write_into_jpeg_without_app0():
    original = _jpeg(_image(3))
    assert original[2:4] == b"\xff\xe0"
    bare = original[:2] + original[4 + int.from_bytes(original[4:6], "big"):]
    tagged = write_gps(bare, lat=-5.5, lon=120.125)
    assert tagged[2:4] == b"\xff\xe1" and tagged[6:12] == b"Exif\x00\x00"
    np.testing.assert_array_equal(decode_image(tagged), decode_image(original))
    assert (read_gps(tagged).lat, read_gps(tagged).lon) == (-5.5, 120.125)


def test_write_keeps_other_exif_tags():
    exif = Image.Exif()
    exif[ExifTags.Base.Make] = "Acme"
    tagged = write_gps(_pillow_jpeg(exif), lat=1.0, lon=1.0)
    assert Image.open(io.BytesIO(tagged)).getexif()[ExifTags.Base.Make] == "Acme"


def test_no_gps_returns_none():
    assert read_gps(_jpeg(_image())) is None
    exif = Image.Exif()
    exif[ExifTags.Base.Make] = "Acme"
    assert read_gps(_pillow_jpeg(exif)) is None


def test_png_exif_is_read():
    exif = Image.Exif()
    exif[ExifTags.IFD.GPSInfo] = {1: "S", 2: (R(12, 1), R(30, 1), R(0, 1)),
                                  3: "E", 4: (R(45, 1), R(15, 1), R(36, 1))}
    tag = read_gps(_pillow_jpeg(exif, "PNG"))
    assert tag == GpsTag(lat=-12.5, lon=45.26, alt=None, captured_at=None)


_ONE = (R(1, 1), R(0, 1), R(0, 1))


@pytest.mark.parametrize(("gps", "message"), [
    ({1: "N", 2: (R(1, 0), R(0, 1), R(0, 1)), 3: "E", 4: _ONE}, "not finite"),
    ({1: "N", 2: (R(95, 1), R(0, 1), R(0, 1)), 3: "E", 4: _ONE}, "within"),
    ({1: "N", 2: _ONE, 3: "E", 4: (R(181, 1), R(0, 1), R(0, 1))}, "within"),
    ({1: "X", 2: _ONE, 3: "E", 4: _ONE}, "must be N or S"),
    ({2: _ONE, 3: "E", 4: _ONE}, "no reference"),
    ({1: "N", 2: _ONE}, "no longitude"),
    ({1: "N", 2: _ONE, 3: "E", 4: _ONE, 5: 7, 6: R(10, 1)}, "altitude reference"),
    ({1: "N", 2: _ONE, 3: "E", 4: _ONE, 6: R(10, 0)}, "altitude is not finite"),
    ({1: "N", 2: (R(1, 1), R(60, 1), R(0, 1)), 3: "E", 4: _ONE}, "below 60"),
    ({1: "N", 2: _ONE, 3: "E", 4: (R(1, 1), R(0, 1), R(6000, 100))}, "below 60"),
    ({1: "N", 2: _ONE, 3: "E", 4: (R(1, 1), R(75, 1))}, "below 60"),
])
def test_malformed_gps_raises(gps, message):
    """Each case is a tag a broken writer could produce; 59.99 minutes or seconds is the
    most a well-formed one holds."""
    exif = Image.Exif()
    exif[ExifTags.IFD.GPSInfo] = gps
    with pytest.raises(GpsError, match=message):
        read_gps(_pillow_jpeg(exif))


def test_gps_error_is_a_value_error_and_void_fix_is_no_position():
    assert issubclass(GpsError, ValueError)
    exif = Image.Exif()
    exif[ExifTags.IFD.GPSInfo] = {1: "N", 2: _ONE, 3: "E", 4: _ONE, 9: "V"}
    assert read_gps(_pillow_jpeg(exif)) is None


@pytest.mark.parametrize(("kwargs", "error"), [
    ({"lat": float("nan"), "lon": 0.0}, GpsError),
    ({"lat": 90.5, "lon": 0.0}, GpsError),
    ({"lat": 0.0, "lon": -180.01}, GpsError),
    ({"lat": 0.0, "lon": 0.0, "alt": float("inf")}, GpsError),
])
def test_write_rejects_bad_positions(kwargs, error):
    with pytest.raises(error):
        write_gps(_jpeg(_image()), **kwargs)


def test_write_rejects_non_jpeg_and_read_rejects_garbage():
    ok, png = cv2.imencode(".png", _image())
    with pytest.raises(ImageError, match="not a JPEG"):
        write_gps(png.tobytes(), lat=0.0, lon=0.0)
    with pytest.raises(ImageError):
        read_gps(b"definitely not an image")
    jpeg = _jpeg(_image())
    # APP0 length overrunning the file: the header cannot be walked to the image data.
    with pytest.raises(ImageError):
        write_gps(jpeg[:2] + b"\xff\xe0\xff\xff" + jpeg[6:200], lat=0.0, lon=0.0)


def test_capture_time_round_trips():
    naive = datetime(2013, 6, 4, 13, 37, 29, 250000)
    assert read_gps(encode_jpeg_with_gps(_image(), lat=1, lon=2, captured_at=naive)) \
        .captured_at == naive
    aware = datetime(2013, 6, 4, 13, 37, 29, 500, tzinfo=timezone(timedelta(hours=-4)))
    got = read_gps(encode_jpeg_with_gps(_image(), lat=1, lon=2, captured_at=aware)).captured_at
    assert got == aware and got.utcoffset() == timedelta(0)


def test_gps_time_stamp_wins_over_date_time_original():
    exif = Image.Exif()
    exif[ExifTags.IFD.Exif] = {ExifTags.Base.DateTimeOriginal: "2020:01:01 09:00:00"}
    exif[ExifTags.IFD.GPSInfo] = {1: "N", 2: _ONE, 3: "E", 4: _ONE, 29: "2020:01:01",
                                  7: (R(14, 1), R(30, 1), R(15, 2))}
    assert read_gps(_pillow_jpeg(exif)).captured_at == datetime(2020, 1, 1, 14, 30, 7, 500000,
                                                                tzinfo=UTC)
    # Without the GPS stamp the camera clock is used; a blank clock gives no time.
    del exif[ExifTags.IFD.GPSInfo]
    exif[ExifTags.IFD.GPSInfo] = {1: "N", 2: _ONE, 3: "E", 4: _ONE}
    assert read_gps(_pillow_jpeg(exif)).captured_at == datetime(2020, 1, 1, 9)
    exif[ExifTags.IFD.Exif] = {ExifTags.Base.DateTimeOriginal: "0000:00:00 00:00:00"}
    assert read_gps(_pillow_jpeg(exif)).captured_at is None


@pytest.mark.dataset
def test_seneca_exif_agrees_with_ground_truth(seneca_dir):
    with open(seneca_dir / "ground_truth.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 167
    for row in rows:
        tag = read_gps((seneca_dir / "images" / row["filename"]).read_bytes())
        assert tag is not None, row["filename"]
        assert abs(tag.lat - float(row["lat"])) < 1e-6, row["filename"]
        assert abs(tag.lon - float(row["lon"])) < 1e-6, row["filename"]
        assert tag.alt == pytest.approx(float(row["alt_m"]), abs=0.01)
        assert tag.captured_at == datetime.fromisoformat(row["captured_at"])
