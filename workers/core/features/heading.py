"""Heading normalisation: turn a frame north-up before describing it.

A device that reports its compass heading lets features that are not rotation invariant
(the grid histograms, WGOH, WGII) see a nadir frame as the map saw it: the frame is rotated
about its centre so that north points to the top of the image.
"""

from __future__ import annotations

import cv2
import numpy as np


def north_up(image: np.ndarray, heading_deg: float) -> np.ndarray:
    """Rotate a frame so that north is up.

    Parameters
    ----------
    image : (H, W) or (H, W, C) uint8 ndarray
    heading_deg : float
        Compass heading of the image's up direction, degrees clockwise from north (0: the
        top of the image points north, 90: east).

    Returns
    -------
    rotated : ndarray of the same shape and dtype
        The image turned clockwise by ``heading_deg`` about the centre of its pixel grid,
        ``((W - 1) / 2, (H - 1) / 2)``, bilinear; pixels that come from outside the frame
        repeat the nearest border pixel (a constant fill would draw edges that gradient
        features would count). At multiples of 90 degrees on a square image, and at 180
        degrees on any image, no pixel is interpolated.
    """
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim not in (2, 3):
        raise ValueError(f"expected an (H, W) or (H, W, C) uint8 image, got {image.dtype} "
                         f"{image.shape}")
    heading = float(heading_deg)
    if not np.isfinite(heading):
        raise ValueError(f"heading must be a finite number of degrees, got {heading_deg!r}")
    heading %= 360.0
    h, w = image.shape[:2]
    if heading == 0.0:
        return image.copy()
    # the image's up points at ``heading``: north lies ``heading`` counter-clockwise of up,
    # so the content turns clockwise by ``heading`` (OpenCV's positive angle turns it
    # counter-clockwise on screen)
    m = cv2.getRotationMatrix2D(((w - 1) / 2.0, (h - 1) / 2.0), -heading, 1.0)
    return cv2.warpAffine(image, m, (w, h), flags=cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_REPLICATE)
