"""EXIF GPS positions: read them from images, write them into JPEGs without re-encoding.

The exploration phase of Erhard et al. (Flyphone, section 3) stores each map image's GPS
position in the EXIF header of the JPEG; the map builder reads positions back from there.
Pillow parses and serialises the EXIF structures; this module only converts between EXIF's
degree/minute/second rationals and signed decimal degrees, and splices the EXIF block into
the JPEG byte stream so that the compressed pixels stay bit-for-bit the same.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta, timezone
from io import BytesIO

import cv2
import numpy as np
from PIL import ExifTags, Image, UnidentifiedImageError
from PIL.TiffImagePlugin import IFDRational

from vloc.workers.core.geo import check_lat_lon
from vloc.workers.core.image import ImageError

_GPS = ExifTags.GPS
_BASE = ExifTags.Base
_MICRO = 10**6
# Seconds of arc with a denominator of 10^6: one unit is 3e-5 m on the ground, far below
# the 1 cm the map needs, and 60 s * 10^6 still fits the 32-bit numerator.
_SECONDS_DENOMINATOR = _MICRO
_ALT_DENOMINATOR = 1000
_MAX_APP1_PAYLOAD = 65533  # the 16-bit segment length counts its own two bytes
_EXIF_HEADER = b"Exif\x00\x00"


class GpsError(ValueError):
    """The image carries GPS tags, but they do not give a usable position."""


@dataclass(frozen=True, slots=True)
class GpsTag:
    """A position read from EXIF.

    Attributes
    ----------
    lat, lon : float
        WGS84 degrees, north and east positive.
    alt : float or None
        Metres above sea level (negative below), None when the image has no altitude.
    captured_at : datetime or None
        Capture time. Timezone-aware (UTC) when it comes from the GPS date/time stamp or
        when EXIF gives the offset; naive local camera time otherwise.
    """

    lat: float
    lon: float
    alt: float | None = None
    captured_at: datetime | None = None


def read_gps(data: bytes) -> GpsTag | None:
    """Read the GPS position and capture time from an image's EXIF.

    Parameters
    ----------
    data : bytes
        A JPEG or PNG file (any format Pillow reads EXIF from).

    Returns
    -------
    GpsTag or None
        None when the image has no GPS position (no GPS block, no latitude/longitude, or
        a receiver status of "V", measurement void).

    Raises
    ------
    ImageError
        The bytes are not an image Pillow can open.
    GpsError
        GPS tags are present but malformed: missing or invalid hemisphere references,
        non-numeric or negative components, minutes or seconds of 60 or more, NaN or
        out-of-range coordinates or altitude.
    """
    exif = _open_exif(data)
    gps = exif.get_ifd(ExifTags.IFD.GPSInfo)
    if _text(gps.get(_GPS.GPSStatus)) == "V":
        return None
    has_lat, has_lon = _GPS.GPSLatitude in gps, _GPS.GPSLongitude in gps
    if not (has_lat or has_lon):
        return None
    if has_lat != has_lon:
        missing = "longitude" if has_lat else "latitude"
        raise GpsError(f"GPS block has no {missing}")
    lat = _signed(gps, _GPS.GPSLatitude, _GPS.GPSLatitudeRef, "NS")
    lon = _signed(gps, _GPS.GPSLongitude, _GPS.GPSLongitudeRef, "EW")
    try:
        check_lat_lon(lat, lon)
    except ValueError as exc:
        raise GpsError(f"malformed GPS position: {exc}") from None
    return GpsTag(lat=lat, lon=lon, alt=_altitude(gps), captured_at=_captured_at(exif, gps))


def write_gps(jpeg: bytes, *, lat: float, lon: float, alt: float | None = None,
              captured_at: datetime | None = None) -> bytes:
    """Return the JPEG with an EXIF GPS position (and capture time) written into it.

    The compressed image data is copied unchanged: only the EXIF APP1 segment is replaced
    (or inserted after SOI and any JFIF APP0), so decoding gives exactly the same pixels.
    Existing EXIF tags are kept, except the GPS block, which is rewritten whole, and the
    embedded thumbnail, which Pillow does not serialise.

    Parameters
    ----------
    jpeg : bytes
        A JPEG file.
    lat, lon : float
        WGS84 degrees. Stored as degree/minute/second rationals with seconds to 1e-6,
        so a round trip is exact to about 3e-5 m.
    alt : float or None
        Metres above sea level; negative values are stored with altitude reference 1.
    captured_at : datetime or None
        Written as DateTimeOriginal (with SubsecTimeOriginal for fractions of a second).
        A timezone-aware time also gets OffsetTimeOriginal and the GPS date/time stamp
        in UTC; a naive time is taken as local camera time and gets no GPS stamp.

    Returns
    -------
    bytes
        The new JPEG file.

    Raises
    ------
    GpsError
        NaN, infinite or out-of-range coordinates or altitude.
    ImageError
        Not a JPEG, or a header too corrupt to find the image data.
    """
    try:
        check_lat_lon(lat, lon)
    except ValueError as exc:
        raise GpsError(str(exc)) from None
    if alt is not None and not math.isfinite(float(alt)):
        raise GpsError(f"alt must be a finite number, got {alt!r}")
    if jpeg[:2] != b"\xff\xd8":
        raise ImageError("not a JPEG file (no SOI marker)")
    exif = _open_exif(jpeg)
    gps = exif.get_ifd(ExifTags.IFD.GPSInfo)
    gps.clear()
    gps.update(_gps_ifd(float(lat), float(lon), alt, captured_at))
    # get_ifd hands back the stored dictionary, so editing it in place edits the EXIF.
    exif[ExifTags.IFD.GPSInfo] = gps
    if captured_at is not None:
        exif.get_ifd(ExifTags.IFD.Exif).update(_time_tags(captured_at))
    payload = exif.tobytes()
    if len(payload) > _MAX_APP1_PAYLOAD:
        raise ImageError(f"EXIF block of {len(payload)} bytes does not fit one APP1 segment")
    return _splice_app1(jpeg, payload)


def encode_jpeg_with_gps(image_bgr: np.ndarray, *, quality: int = 90, lat: float, lon: float,
                         alt: float | None = None,
                         captured_at: datetime | None = None) -> bytes:
    """Encode a BGR image as JPEG and tag it with a GPS position.

    Parameters
    ----------
    image_bgr : (H, W, 3) uint8 ndarray, BGR
    quality : int
        JPEG quality, 1 to 100.
    lat, lon, alt, captured_at
        As for :func:`write_gps`.

    Returns
    -------
    bytes
        A JPEG file with EXIF GPS.
    """
    if not 1 <= int(quality) <= 100:
        raise ValueError(f"quality must be within 1..100, got {quality}")
    ok, buf = cv2.imencode(".jpg", image_bgr, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ImageError(f"could not encode an image of shape {image_bgr.shape} as JPEG")
    return write_gps(buf.tobytes(), lat=lat, lon=lon, alt=alt, captured_at=captured_at)


def _open_exif(data: bytes) -> Image.Exif:
    try:
        with Image.open(BytesIO(data)) as im:
            return im.getexif()
    except (UnidentifiedImageError, OSError) as exc:
        raise ImageError(f"not a readable image: {exc}") from None
    except (SyntaxError, ValueError, TypeError, KeyError, IndexError) as exc:
        # Pillow raises these from inside a damaged TIFF/EXIF structure.
        raise GpsError(f"unreadable EXIF block: {exc}") from None


def _text(value) -> str | None:
    if value is None:
        return None
    if isinstance(value, bytes):
        value = value.decode("ascii", errors="replace")
    return str(value).strip("\x00 \t").upper() or None


def _floats(value, what: str) -> list[float]:
    parts = value if isinstance(value, tuple | list) else (value,)
    try:
        numbers = [float(p) for p in parts]
    except (TypeError, ValueError):
        raise GpsError(f"{what} is not numeric: {value!r}") from None
    if not all(math.isfinite(v) for v in numbers):
        raise GpsError(f"{what} is not finite: {numbers}")
    return numbers


def _signed(gps: dict, value_tag: int, ref_tag: int, refs: str) -> float:
    """Degrees/minutes/seconds and an N/S or E/W reference -> signed degrees."""
    what = "latitude" if refs == "NS" else "longitude"
    parts = _floats(gps[value_tag], f"GPS {what}")
    if not 1 <= len(parts) <= 3 or min(parts) < 0:
        raise GpsError(f"GPS {what} must be 1 to 3 non-negative numbers, got {parts}")
    if any(p >= 60.0 for p in parts[1:]):
        # 0..59.99 minutes and seconds; 60 or more is a writer's arithmetic error, and
        # reading it as is would move the position by whole minutes of arc.
        raise GpsError(f"GPS {what} minutes and seconds must be below 60, got {parts}")
    degrees = sum(p / 60.0**i for i, p in enumerate(parts))
    ref = _text(gps.get(ref_tag))
    if ref is None:
        # Guessing a hemisphere could put the image on the wrong side of the planet.
        raise GpsError(f"GPS {what} has no reference ({refs[0]}/{refs[1]})")
    if ref not in refs:
        raise GpsError(f"GPS {what} reference must be {refs[0]} or {refs[1]}, got {ref!r}")
    return -degrees if ref == refs[1] else degrees


def _altitude(gps: dict) -> float | None:
    if _GPS.GPSAltitude not in gps:
        return None
    values = _floats(gps[_GPS.GPSAltitude], "GPS altitude")
    if len(values) != 1 or values[0] < 0:
        raise GpsError(f"GPS altitude must be one non-negative number, got {values}")
    alt = values[0]
    ref = gps.get(_GPS.GPSAltitudeRef, 0)
    if isinstance(ref, bytes):
        ref = ref[0] if ref else 0
    if ref not in (0, 1):
        raise GpsError(f"GPS altitude reference must be 0 or 1, got {ref!r}")
    return -abs(alt) if ref == 1 else alt


def _captured_at(exif: Image.Exif, gps: dict) -> datetime | None:
    """GPS date/time stamp (UTC) first, then DateTimeOriginal, then DateTime."""
    stamp = _gps_time(gps)
    if stamp is not None:
        return stamp
    sub = exif.get_ifd(ExifTags.IFD.Exif)
    for where, tag, subsec, offset in (
        (sub, _BASE.DateTimeOriginal, _BASE.SubsecTimeOriginal, _BASE.OffsetTimeOriginal),
        (exif, _BASE.DateTime, _BASE.SubsecTime, _BASE.OffsetTime),
    ):
        when = _exif_time(where.get(tag), sub.get(subsec), sub.get(offset))
        if when is not None:
            return when
    return None


def _gps_time(gps: dict) -> datetime | None:
    date, time = _text(gps.get(_GPS.GPSDateStamp)), gps.get(_GPS.GPSTimeStamp)
    if date is None or time is None:
        return None
    try:
        day = datetime.strptime(date, "%Y:%m:%d").replace(tzinfo=UTC)
        h, m, s = _floats(time, "GPS time stamp")
    except (ValueError, GpsError):
        return None  # a capture time is optional; a damaged one is treated as absent
    seconds = round((h * 3600 + m * 60 + s) * _MICRO) / _MICRO
    return day + timedelta(seconds=seconds)


def _exif_time(value, subsec, offset) -> datetime | None:
    text = _text(value)
    if text is None:
        return None
    try:
        when = datetime.strptime(text[:19], "%Y:%m:%d %H:%M:%S")
    except ValueError:
        return None  # cameras without a clock write blanks or "0000:00:00 00:00:00"
    digits = (_text(subsec) or "").strip()
    if digits.isdigit():
        when = when.replace(microsecond=int(digits[:6].ljust(6, "0")))
    zone = _text(offset)
    if zone and len(zone) == 6 and zone[0] in "+-" and zone[3] == ":":
        try:
            delta = timedelta(hours=int(zone[1:3]), minutes=int(zone[4:6]))
        except ValueError:
            return when
        when = when.replace(tzinfo=timezone(-delta if zone[0] == "-" else delta))
    return when


def _dms(value: float) -> tuple[IFDRational, IFDRational, IFDRational]:
    """|degrees| -> exact degree, minute, micro-second rationals (integer arithmetic)."""
    total = round(abs(value) * 3600 * _SECONDS_DENOMINATOR)
    degrees, rest = divmod(total, 3600 * _SECONDS_DENOMINATOR)
    minutes, seconds = divmod(rest, 60 * _SECONDS_DENOMINATOR)
    return IFDRational(degrees, 1), IFDRational(minutes, 1), \
        IFDRational(seconds, _SECONDS_DENOMINATOR)


def _gps_ifd(lat: float, lon: float, alt: float | None,
             captured_at: datetime | None) -> dict[int, object]:
    tags: dict[int, object] = {
        _GPS.GPSVersionID: b"\x02\x03\x00\x00",
        _GPS.GPSLatitudeRef: "N" if lat >= 0 else "S",
        _GPS.GPSLatitude: _dms(lat),
        _GPS.GPSLongitudeRef: "E" if lon >= 0 else "W",
        _GPS.GPSLongitude: _dms(lon),
    }
    if alt is not None:
        tags[_GPS.GPSAltitudeRef] = 1 if alt < 0 else 0
        tags[_GPS.GPSAltitude] = IFDRational(round(abs(alt) * _ALT_DENOMINATOR),
                                             _ALT_DENOMINATOR)
    if captured_at is not None and captured_at.tzinfo is not None:
        utc = captured_at.astimezone(UTC)
        tags[_GPS.GPSDateStamp] = utc.strftime("%Y:%m:%d")
        tags[_GPS.GPSTimeStamp] = (IFDRational(utc.hour, 1), IFDRational(utc.minute, 1),
                                   IFDRational(utc.second * _MICRO + utc.microsecond, _MICRO))
    return tags


def _time_tags(captured_at: datetime) -> dict[int, str]:
    tags = {_BASE.DateTimeOriginal: captured_at.strftime("%Y:%m:%d %H:%M:%S")}
    if captured_at.microsecond:
        tags[_BASE.SubsecTimeOriginal] = f"{captured_at.microsecond:06d}"
    offset = captured_at.utcoffset()
    if offset is not None:
        minutes = round(offset.total_seconds() / 60)
        sign = "-" if minutes < 0 else "+"
        tags[_BASE.OffsetTimeOriginal] = f"{sign}{abs(minutes) // 60:02d}:{abs(minutes) % 60:02d}"
    return tags


def _splice_app1(jpeg: bytes, payload: bytes) -> bytes:
    """Replace the EXIF APP1 segment(s) of a JPEG by one holding ``payload``."""
    segments, image_start = _header_segments(jpeg)
    app1 = b"\xff\xe1" + (len(payload) + 2).to_bytes(2, "big") + payload
    out = [jpeg[:2]]
    inserted = False
    for marker, start, end in segments:
        # JFIF readers expect APP0 straight after SOI, so EXIF goes after it.
        if not inserted and marker != 0xE0:
            out.append(app1)
            inserted = True
        if marker == 0xE1 and jpeg[start + 4:start + 10] == _EXIF_HEADER:
            continue
        out.append(jpeg[start:end])
    if not inserted:
        out.append(app1)
    out.append(jpeg[image_start:])
    return b"".join(out)


def _header_segments(jpeg: bytes) -> tuple[list[tuple[int, int, int]], int]:
    """(marker, start, end) of each segment between SOI and SOS, and where SOS starts."""
    segments = []
    pos = 2
    while pos + 1 < len(jpeg):
        if jpeg[pos] != 0xFF:
            raise ImageError(f"corrupt JPEG: no marker at byte {pos}")
        marker = jpeg[pos + 1]
        if marker == 0xFF:  # fill byte before a marker
            pos += 1
            continue
        if marker in (0xDA, 0xD9):  # start of scan / end of image: header is over
            return segments, pos
        if marker == 0x01 or 0xD0 <= marker <= 0xD7:  # markers without a length
            segments.append((marker, pos, pos + 2))
            pos += 2
            continue
        length = int.from_bytes(jpeg[pos + 2:pos + 4], "big")
        if length < 2 or pos + 2 + length > len(jpeg):
            raise ImageError(f"corrupt JPEG: segment at byte {pos} overruns the file")
        segments.append((marker, pos, pos + 2 + length))
        pos += 2 + length
    raise ImageError("corrupt JPEG: no image data (SOS marker) found")
