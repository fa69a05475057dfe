"""One image localised against a packed revision, run by the engine's workers
(:func:`vloc.app.engine.run_task`) for ``POST /v1/maps/{id}/localize``: one step of a fresh
particle filter over the map, started around the prior position when one is given. Nothing
is stored. The map and the step are the ones a session's worker uses
(:func:`~vloc.workers.core.mapdata.open_map`,
:func:`~vloc.workers.core.stepping.step_image`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from vloc.workers.core.metadata import FrameMetadata


def localize_image(folder: str, data: bytes, *, mode: str, params: dict, seed: int,
                   prior: tuple[float, float, float] | None, metadata: FrameMetadata | None,
                   max_pixels: int) -> dict:
    """Step a new localiser once on the image.

    ``prior`` is (lat, lon, sigma metres). Returns ``estimate`` (the localiser's
    :class:`~workers.core.estimate.Estimate`) and ``decode_ms``; a ValueError
    for an image that cannot be decoded or a prior outside the map's frame.
    """
    from vloc.workers.core.image import ImageError
    from vloc.workers.core.localisers import make_localiser
    from vloc.workers.core.mapdata import open_map
    from vloc.workers.core.stepping import step_image

    map_data = open_map(folder)
    localiser = make_localiser(mode, map_data, params, seed=seed)
    if prior is not None:
        east, north = map_data.origin.to_local(prior[0], prior[1])
        localiser.set_initial_pose(float(east), float(north), prior[2])
    try:
        record = step_image(localiser, data, max_pixels=max_pixels, metadata=metadata)
    except ImageError as exc:
        raise ValueError(f"bad image: {exc}") from None
    return {"estimate": record.estimate, "decode_ms": record.decode_ms}
