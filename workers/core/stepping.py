"""One frame through a localiser, as every caller runs it: decode, step, to record.

A session's worker and the one-shot localisation of a single image both go through
:func:`step_image`, so a frame is decoded, stepped and reported the same way whichever asked.
It imports no localiser: the one it steps comes from the caller.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

from .estimate import Estimate
from .image import Header, load_frame
from .metadata import FrameMetadata

# Only for the annotation: the localisers' package imports every localiser, which a worker
# would pay for on its first frame (a shard restarted by Ray, on its first after that).
if TYPE_CHECKING:
    from .localisers.base import Localiser


@dataclass(frozen=True, slots=True)
class StepRecord:
    """What one step reports: the localiser's ``estimate`` as it made it (it crosses the
    process boundary as it is, and the API process writes its message once) and
    ``decode_ms``, the milliseconds the image took to decode."""

    estimate: Estimate
    decode_ms: float


def step_image(localiser: Localiser, data: bytes, *, max_pixels: int,
               captured_at: float | None = None, metadata: FrameMetadata | None = None,
               header: Header | None = None) -> StepRecord:
    """Decode an encoded image (JPEG or PNG bytes) and step ``localiser`` on it once.

    ``metadata`` is the frame's sensor reports, validated where they arrived;
    ``header`` what its file header says, where it was read already. Raises
    :class:`~workers.core.image.ImageError` (a ValueError) for bytes that do not decode,
    before the localiser is touched; anything the step raises passes through.
    """
    t0 = time.perf_counter()
    frame = load_frame(data, max_pixels=max_pixels, header=header)
    decode_ms = (time.perf_counter() - t0) * 1e3
    estimate = localiser.step(frame, captured_at=captured_at, metadata=metadata)
    return StepRecord(estimate, decode_ms)
