"""Where was this one image taken? A synchronous, sessionless localisation.

The route (:func:`localize`) checks the request and the map, then runs
:func:`localize_in_worker` on the least busy worker of the engine: one step of a fresh
particle filter over the map (SIFT by default), started around the prior position when one
is given. Nothing is stored.
"""

from __future__ import annotations

import time
from functools import lru_cache

from vloc.app.problems import Problem

MODES = ("sift", "global", "hybrid")
"""The localisers one image can use: the particle filter's, for one step."""
DEFAULT_PRIOR_SIGMA_M = 25.0


@lru_cache(maxsize=4)
def _map(folder: str):
    """Worker side: a packed revision, loaded (memory-mapped) once per worker process."""
    from vloc.workers.core.mapdata import MapData

    return MapData.load(folder, mmap=True)


def localize_in_worker(folder: str, data: bytes, *, mode: str, params: dict, seed: int,
                       prior: tuple[float, float, float] | None, metadata: dict | None,
                       max_pixels: int) -> dict:
    """Worker side: decode the image and step a new localiser once.

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


def check_prior(lat: float | None, lon: float | None, sigma_m: float | None
                ) -> tuple[float, float, float] | None:
    """The prior position, or None; 422 ``bad-prior`` for half a pair or a sigma without
    a position (ranges are checked by the query parser)."""
    if lat is None and lon is None:
        if sigma_m is not None:
            raise Problem(422, "prior_sigma_m needs prior_lat and prior_lon",
                          kind="bad-prior", field="prior_sigma_m")
        return None
    if lat is None or lon is None:
        missing = "prior_lat" if lat is None else "prior_lon"
        raise Problem(422, "prior_lat and prior_lon come together", kind="bad-prior",
                      field=missing)
    return lat, lon, sigma_m if sigma_m is not None else DEFAULT_PRIOR_SIGMA_M
