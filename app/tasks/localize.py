"""One image localised against a packed revision, run by the engine's workers
(:func:`vloc.app.engine.run_task`) for ``POST /v1/maps/{id}/localize``: one step of a fresh
particle filter over the map, started around the prior position when one is given. Nothing
is stored.
"""

from __future__ import annotations

import time
from functools import lru_cache


@lru_cache(maxsize=4)
def _map(folder: str):
    """A packed revision, loaded (memory-mapped) once per worker process."""
    from vloc.workers.core.mapdata import MapData

    return MapData.load(folder, mmap=True)


def localize_image(folder: str, data: bytes, *, mode: str, params: dict, seed: int,
                   prior: tuple[float, float, float] | None, metadata: dict | None,
                   max_pixels: int) -> dict:
    """Decode the image and step a new localiser once.

    ``prior`` is (lat, lon, sigma metres). Returns ``estimate``
    (:meth:`~workers.core.estimate.Estimate.to_dict`) and ``decode_ms``; a ValueError
    for an image that cannot be decoded or a prior outside the map's frame.
    """
    from vloc.workers.core.image import ImageError, load_frame
    from vloc.workers.core.localisers import make_localiser
    from vloc.workers.core.metadata import FrameMetadata

    t0 = time.perf_counter()
    try:
        frame = load_frame(data, max_pixels=max_pixels)
    except ImageError as exc:
        raise ValueError(f"bad image: {exc}") from None
    decode_ms = (time.perf_counter() - t0) * 1e3
    map_data = _map(folder)
    localiser = make_localiser(mode, map_data, params, seed=seed)
    if prior is not None:
        east, north = map_data.origin.to_local(prior[0], prior[1])
        localiser.set_initial_pose(float(east), float(north), prior[2])
    estimate = localiser.step(frame, metadata=FrameMetadata.from_dict(metadata))
    return {"estimate": estimate.to_dict(), "decode_ms": decode_ms}
