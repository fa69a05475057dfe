"""A map that measures itself: its own images localised against the rest of it.

At build time every placed map image (a spread sample of :data:`SAMPLE` on large maps) is
localised the way a frame's SIFT step localises it once the filter has found its place
(:func:`workers.core.localisers.refine.refine_sift`): its stored SIFT matched against the
map images nearest it, not itself, and a pose solved from the matched 3-D points. Compared
with the image's GPS, that gives the map's own error figure (mean, median, share within
5 m) and how often it registers at all, beside the nearest-image floor: how far each image
lies from its nearest other map image, which is the best a position taken from the map's
images alone can do. A map whose geometry does no better than that floor is not given any
(a reconstruction that is wrong, however consistent it looks), and one that does gets its
registrations' accuracy from its own median error.

The images' own tie points helped place the 3-D points they are matched to, so the check is
a little kinder than a new frame would find the map; `vloc eval` measures that.
"""

from __future__ import annotations

import math

import numpy as np

from .geometry import MapGeometry
from .image import WORK_SIZE
from .localisers.refine import refine_sift
from .mapdata import MapData

SAMPLE: int = 300
"""Most map images localised by the check."""

NEIGHBOURS: int = 4
"""Map images (the nearest by GPS, not itself) an image is matched against."""

MIN_REGISTERED: float = 0.4
"""A geometry that registers fewer than this share of the checked images is refused."""

SIGMA_FLOOR: float = 2.0
"""Least standard deviation (m) a registration is fused with."""


def self_check(data: MapData, geometry: MapGeometry, *, seed: int = 0) -> MapGeometry | None:
    """Localise the map's images against the rest of it; ``geometry`` with its figures
    (``geometry.self_check``), or None where it does no better than the nearest image.

    The figures: ``images`` checked, ``registered`` share, ``mean_m``, ``median_m`` and
    ``within_5m`` of the registered ones' distance to their GPS, ``floor_mean_m`` and
    ``floor_median_m`` (each checked image's distance to its nearest other map image),
    ``sigma_m`` (the standard deviation registrations are fused with) and ``trusted``.
    """
    positions = np.asarray(data.positions)
    placed = np.flatnonzero(geometry.reconstructed)
    n = len(positions)
    if len(placed) == 0 or n < NEIGHBOURS + 1:
        return None
    sample = placed[np.linspace(0, len(placed) - 1, min(SAMPLE, len(placed))).round()
                    .astype(np.int64)]
    sample = np.unique(sample)
    previous, data.geometry = data.geometry, geometry
    try:
        errors, floors = [], []
        _, near = data.tree.query(positions[sample], k=NEIGHBOURS + 1)
        for i, nb in zip(sample.tolist(), near, strict=True):
            others = np.array([j for j in nb.tolist() if j != i][:NEIGHBOURS])
            floors.append(float(np.min([np.hypot(*(positions[j] - positions[i]))
                                        for j in others])))
            fix = refine_sift(data.sift(i), data, others, np.ones(len(others)),
                              frame_shape=(WORK_SIZE[1], WORK_SIZE[0]))
            if fix is not None and fix.kind == "registered":
                errors.append(float(np.hypot(*(fix.xy - positions[i]))))
    finally:
        data.geometry = previous
    errors_a, floors_a = np.asarray(errors), np.asarray(floors)
    figures = {"images": len(sample), "registered": len(errors) / len(sample),
               "floor_mean_m": float(floors_a.mean()),
               "floor_median_m": float(np.median(floors_a))}
    if len(errors_a):
        figures.update(mean_m=float(errors_a.mean()), median_m=float(np.median(errors_a)),
                       within_5m=float(np.mean(errors_a <= 5.0)))
    trusted = (figures["registered"] >= MIN_REGISTERED and len(errors_a) > 0
               and figures["median_m"] < figures["floor_median_m"])
    figures["trusted"] = bool(trusted)
    figures["sigma_m"] = (max(SIGMA_FLOOR, 1.25 * figures["median_m"]) if len(errors_a)
                          else math.nan)
    geometry.self_check = figures
    return geometry if trusted else None

