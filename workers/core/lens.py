"""The camera's focal length from EXIF, in pixels at the working resolution.

Camera geometry (:mod:`workers.core.geometry`) needs the focal length in pixels. EXIF gives it
in two ways: the focal length in millimetres with the focal-plane resolution (sensor pixels per
inch, centimetre or millimetre at the EXIF image width), or the 35 mm-equivalent focal length
(a 36 mm wide frame). Either is converted to pixels at the width the frames are worked at.
"""

from __future__ import annotations

import math
from io import BytesIO

from PIL import ExifTags, Image

from .geometry import focal_from_exif

_BASE = ExifTags.Base
_MM_PER_UNIT = {2: 25.4, 3: 10.0, 4: 1.0, 5: 1e-3}
"""FocalPlaneResolutionUnit -> millimetres: inch, centimetre, millimetre, micrometre."""

FULL_FRAME_WIDTH_MM = 36.0


def read_focal_px(data: bytes, width: int) -> float | None:
    """Focal length in pixels at ``width`` pixels across, or None when EXIF does not say.

    Parameters
    ----------
    data : bytes
        An image file.
    width : int
        The width the frame is resized to (the working resolution).
    """
    try:
        with Image.open(BytesIO(data)) as im:
            exif = im.getexif().get_ifd(ExifTags.IFD.Exif)
            image_width = im.width
    except Exception:  # noqa: BLE001 - any unreadable header simply gives no lens
        return None
    focal_mm = _number(exif.get(_BASE.FocalLength))
    plane_res = _number(exif.get(_BASE.FocalPlaneXResolution))
    unit = int(_number(exif.get(_BASE.FocalPlaneResolutionUnit)) or 2)
    exif_width = _number(exif.get(_BASE.ExifImageWidth)) or image_width
    if plane_res is not None and unit in _MM_PER_UNIT:
        f = focal_from_exif(focal_mm, plane_res / _MM_PER_UNIT[unit], exif_width, width)
        if f is not None:
            return f
    f35 = _number(exif.get(_BASE.FocalLengthIn35mmFilm))
    if f35:
        return focal_from_exif(f35, 1.0, FULL_FRAME_WIDTH_MM, width)
    return None


def _number(value) -> float | None:
    try:
        x = float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return x if math.isfinite(x) and x > 0 else None
