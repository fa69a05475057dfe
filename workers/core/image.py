"""Decoding and preparing images at the working resolution.

All algorithms work on a :class:`Frame`: the image resized to the working resolution
(default 320x240, as in Weiss et al. 2008 and Erhard et al.), kept both as 8-bit grey and
as 8-bit BGR colour for the features that need colour (the hue histogram).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np

WORK_SIZE: tuple[int, int] = (320, 240)
"""Working resolution as (width, height)."""

MAX_PIXELS: int = 50_000_000
"""Default decompression-bomb guard: images with more pixels than this are refused."""


class ImageError(ValueError):
    """The bytes are not a usable image (corrupt, truncated, empty, too large)."""


@dataclass(frozen=True, slots=True)
class Frame:
    """One image at the working resolution.

    Attributes
    ----------
    grey : (H, W) uint8 ndarray
    colour : (H, W, 3) uint8 ndarray, BGR channel order (OpenCV convention)
    """

    grey: np.ndarray
    colour: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        return self.grey.shape  # type: ignore[return-value]


class Header(NamedTuple):
    """What an image's file header says: its size and, for a JPEG, its EXIF orientation
    (1: stored as it is seen; None: its EXIF could not be read)."""

    width: int
    height: int
    orientation: int | None = 1


_EXIF_ORIENTATION = 0x0112


def orientation_of(im) -> int | None:
    """The EXIF orientation of an image Pillow opened (1 where it has none or is no JPEG;
    None where its EXIF cannot be read). Only the header is read."""
    if im.format != "JPEG" or "exif" not in im.info:
        return 1
    try:
        return int(im.getexif().get(_EXIF_ORIENTATION, 1))
    except Exception:  # noqa: BLE001 - unreadable EXIF: unknown, OpenCV decides
        return None


def read_header(data: bytes) -> Header | None:
    """The file header (size, orientation) without decoding the pixels, where readable."""
    from io import BytesIO

    from PIL import Image

    try:
        with Image.open(BytesIO(data)) as im:
            return Header(*im.size, orientation_of(im))
    except Exception:  # noqa: BLE001 - any header failure means "unknown", decided below
        return None


_REDUCED = ((8, cv2.IMREAD_REDUCED_COLOR_8), (4, cv2.IMREAD_REDUCED_COLOR_4),
            (2, cv2.IMREAD_REDUCED_COLOR_2))


def decode_image(data: bytes, *, max_pixels: int = MAX_PIXELS,
                 min_size: tuple[int, int] | None = None,
                 header: Header | None = None) -> np.ndarray:
    """Decode JPEG/PNG bytes into a BGR image.

    Parameters
    ----------
    data : bytes
        The encoded file.
    max_pixels : int
        Refuse images whose header declares more pixels than this (decompression bombs)
        before any pixel is decoded.
    min_size : (width, height) or None
        The image will be shrunk to this size: a JPEG may then be decoded at 1/2, 1/4 or
        1/8 scale straight from its DCT coefficients (much faster), as long as the
        result stays at least this large.
    header : Header or None
        Its header, where the caller read it already (the API process checks every
        frame's header before it reaches a worker): not read again.

    Returns
    -------
    image : (H, W, 3) uint8 ndarray, BGR

    Raises
    ------
    ImageError
        Empty, corrupt, truncated or oversized input.
    """
    if not data:
        raise ImageError("empty image")
    if header is None:
        header = read_header(data)
    if header is None:
        raise ImageError("not a decodable JPEG or PNG image")
    width, height = header.width, header.height
    if width <= 0 or height <= 0:
        raise ImageError("image has no pixels")
    if width * height > max_pixels:
        raise ImageError(
            f"image of {width}x{height} pixels exceeds the limit of {max_pixels} pixels"
        )
    flag, scale = cv2.IMREAD_COLOR, 1
    if min_size is not None and data[:2] == b"\xff\xd8":
        for factor, reduced in _REDUCED:
            if width // factor >= min_size[0] and height // factor >= min_size[1]:
                flag, scale = reduced, factor
                break
    if looks_truncated(data):
        raise ImageError("truncated image")
    if data[:2] == b"\xff\xd8":
        image = _decode_jpeg(data, header, scale)
        if image is not None:
            return image
    buf = np.frombuffer(data, dtype=np.uint8)
    image = cv2.imdecode(buf, flag)
    if image is None:
        raise ImageError("corrupt or truncated image")
    return image


_JPEG_COLOURS = {"Gray": "GRAY", "YCbCr": "GRAY", "RGB": "GRAY", "CMYK": "CMYK",
                 "YCCK": "CMYK"}


def _decode_jpeg(data: bytes, header: Header, scale: int) -> np.ndarray | None:
    """A JPEG decoded once, strictly, at ``1/scale`` of its size, as OpenCV would decode it;
    None where OpenCV must decode it (a colour space other than grey or YCbCr, or an EXIF
    orientation to apply, which OpenCV applies), once its blocks are checked.

    libjpeg fills the blocks of a stream cut short with grey and only warns (an end marker
    appended to half a file decodes "successfully"), and OpenCV ignores the warning;
    libjpeg-turbo in strict mode (simplejpeg's) turns it into an error. OpenCV's decoder and
    simplejpeg are both libjpeg-turbo with its default (accurate) inverse DCT and
    upsampling, so their pixels are the same (the tests hold them to it): one strict decode
    does both. Where OpenCV decodes, the strict pass is at 1/8 scale: the whole
    entropy-coded stream is read, only the inverse DCTs are cheaper.
    """
    import simplejpeg

    try:
        height, width, colour, _ = simplejpeg.decode_jpeg_header(data)
    except ValueError as exc:
        raise ImageError(f"corrupt or incomplete JPEG data ({exc})") from None
    if (width, height) != (header.width, header.height):
        raise ImageError(f"the JPEG's frame header says {width}x{height}, its file "
                         f"header {header.width}x{header.height}")
    ours = colour in ("Gray", "YCbCr") and header.orientation == 1
    try:
        if ours:
            return simplejpeg.decode_jpeg(data, colorspace="BGR", strict=True,
                                          min_width=-(-width // scale),
                                          min_height=-(-height // scale))
        simplejpeg.decode_jpeg(data, colorspace=_JPEG_COLOURS.get(colour, "GRAY"),
                               strict=True, min_height=1, min_width=1)
    except ValueError as exc:
        raise ImageError(f"corrupt or incomplete JPEG data ({exc})") from None
    return None


def image_kind(data: bytes) -> str | None:
    """``"jpeg"`` or ``"png"`` from the magic bytes, else None."""
    if data[:3] == b"\xff\xd8\xff":
        return "jpeg"
    if data[:8] == b"\x89PNG\r\n\x1a\n":
        return "png"
    return None


def identify(data: bytes) -> tuple[str | None, bool]:
    """The image's kind (:func:`image_kind`) and whether its stream looks truncated
    (:func:`looks_truncated`), in one call: what the API checks of every upload and frame."""
    return image_kind(data), looks_truncated(data)


def looks_truncated(data: bytes) -> bool:
    """JPEG streams must end with the EOI marker; PNG streams with the IEND chunk.

    OpenCV silently fills a truncated JPEG with grey, so the check is explicit. The API
    applies the same check to uploads before storing them (:mod:`app.imagecheck`).
    """
    tail = data.rstrip(b"\x00")[-12:]
    if data[:2] == b"\xff\xd8":
        return not tail.endswith(b"\xff\xd9")
    if data[:8] == b"\x89PNG\r\n\x1a\n":
        return b"IEND" not in tail
    return False


def prepare(image: np.ndarray, size: tuple[int, int] = WORK_SIZE) -> Frame:
    """Resize an image to the working resolution.

    Parameters
    ----------
    image : (H, W, 3) uint8 BGR or (H, W) uint8 grey ndarray
    size : (width, height)

    Returns
    -------
    Frame
    """
    if image.ndim == 2:
        image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise ImageError(f"expected an 8-bit BGR image, got {image.dtype} {image.shape}")
    if (image.shape[1], image.shape[0]) != size:
        # INTER_AREA: the right filter for downsampling, no aliasing of fine texture.
        image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    colour = np.ascontiguousarray(image)
    grey = cv2.cvtColor(colour, cv2.COLOR_BGR2GRAY)
    return Frame(grey=grey, colour=colour)


def load_frame(data: bytes, *, size: tuple[int, int] = WORK_SIZE,
               max_pixels: int = MAX_PIXELS,
               header: Header | None = None) -> Frame:
    """Decode and prepare in one call (``header``: :func:`decode_image`)."""
    return prepare(decode_image(data, max_pixels=max_pixels, min_size=size,
                                header=header), size)
