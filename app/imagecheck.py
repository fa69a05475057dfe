"""Header-level checks of an image upload, done in the API process before anything is stored.

Only the file header is parsed here (format, pixel size, end marker): enough to refuse empty,
non-image, truncated and decompression-bomb uploads at once with the right status. Pixel
decoding happens in the workers.
"""

from __future__ import annotations

import re
import warnings
from dataclasses import dataclass
from io import BytesIO

from PIL import Image, UnidentifiedImageError

from vloc.app.problems import Problem, ProblemKind
from vloc.workers.core.image import Header, identify, image_kind, orientation_of

CONTENT_TYPES = {"jpeg": "image/jpeg", "png": "image/png"}
_KIND_OF_TYPE = {v: k for k, v in CONTENT_TYPES.items()} | {"image/jpg": "jpeg"}


@dataclass(frozen=True, slots=True)
class ImageHeader:
    kind: str
    width: int
    height: int
    orientation: int | None = 1
    """A JPEG's EXIF orientation (1: as stored; None: unreadable EXIF)."""

    @property
    def core(self) -> Header:
        """What the worker's decode needs of it, so that it does not read it again."""
        return Header(self.width, self.height, self.orientation)

    @property
    def content_type(self) -> str:
        return CONTENT_TYPES[self.kind]

    @property
    def suffix(self) -> str:
        return ".jpg" if self.kind == "jpeg" else ".png"


sniff = image_kind
"""``"jpeg"`` or ``"png"`` from the magic bytes, else None (the core's check)."""


def kind_of_content_type(content_type: str | None) -> str | None:
    """``image/jpeg; q=1`` -> ``"jpeg"``; None for anything but JPEG and PNG."""
    if not content_type:
        return None
    return _KIND_OF_TYPE.get(content_type.split(";")[0].strip().lower())


def check_image(data: bytes, *, max_pixels: int, declared: str | None = None) -> ImageHeader:
    """Check an encoded image from its header.

    Parameters
    ----------
    data : bytes
    max_pixels : int
        Width x height above which the image is refused as a decompression bomb.
    declared : ``"jpeg"``, ``"png"`` or None
        The kind the client declared (Content-Type); it must match the bytes.

    Raises
    ------
    Problem
        422 empty, unreadable or truncated; 415 bytes of another kind than declared;
        413 more pixels than allowed.
    """
    if not data:
        raise Problem(422, "the image is empty", kind=ProblemKind.EMPTY_IMAGE)
    kind, truncated = identify(data)
    if kind is None:
        raise Problem(422, "not a JPEG or PNG image", kind=ProblemKind.BAD_IMAGE)
    if declared is not None and kind != declared:
        raise Problem(415, f"the body is a {kind.upper()} image, but the content type says "
                      f"{declared.upper()}", kind=ProblemKind.CONTENT_TYPE_MISMATCH)
    width, height, orientation = _header(data, max_pixels)
    if width <= 0 or height <= 0:
        raise Problem(422, "the image has no pixels", kind=ProblemKind.BAD_IMAGE)
    if width * height > max_pixels:
        raise Problem(413, f"an image of {width}x{height} pixels exceeds the limit of "
                      f"{max_pixels} pixels", kind=ProblemKind.TOO_MANY_PIXELS, max_pixels=max_pixels)
    if truncated:
        raise Problem(422, "the image is truncated", kind=ProblemKind.TRUNCATED_IMAGE)
    return ImageHeader(kind, width, height, orientation)


def _header(data: bytes, max_pixels: int) -> tuple[int, int, int | None]:
    """Width, height and EXIF orientation, from the header only."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(BytesIO(data)) as im:
                size = im.size
                if im.format == "PNG" and size[0] * size[1] <= max_pixels:
                    # PNG chunk CRCs are checked without inflating the pixels.
                    im.verify()
                return (*size, orientation_of(im))
    except Image.DecompressionBombError as exc:
        raise Problem(413, str(exc), kind=ProblemKind.TOO_MANY_PIXELS, max_pixels=max_pixels) from None
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError, EOFError) as exc:
        if "truncated" in str(exc).lower() or isinstance(exc, EOFError):
            raise Problem(422, "the image is truncated", kind=ProblemKind.TRUNCATED_IMAGE) from None
        raise Problem(422, f"the image header is unreadable: {_describe(exc)}",
                      kind=ProblemKind.BAD_IMAGE) from None


def _describe(exc: Exception) -> str:
    """Pillow's message without the repr of our in-memory file (``<_io.BytesIO ...>``)."""
    if isinstance(exc, UnidentifiedImageError):
        return "not an image Pillow can identify"
    return _OBJECT_REPR.sub("the image", str(exc)) or type(exc).__name__


_OBJECT_REPR = re.compile(r"<[^<>]*\bobject at 0x[0-9a-fA-F]+>")
