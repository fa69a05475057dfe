"""Uploads checked in the workers: full decoding never runs in the API process."""

from __future__ import annotations


def inspect_image(data: bytes, *, max_pixels: int) -> tuple[int, int]:
    """Decode an image fully; (width, height), or ImageError (a ValueError)."""
    from vloc.workers.core.image import decode_image

    image = decode_image(data, max_pixels=max_pixels)
    return int(image.shape[1]), int(image.shape[0])
