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

Those figures speak for the images the geometry registers. What a user wants to know is what
to expect of the map as a whole, over its images that no pose reaches too: the ``every_image``
figures count every map image (a spread sample of them), one that registers at its error and
one that does not at its nearest-image distance, the best a position between the images it
matched can do. Against the mean error `vloc eval` measures on seneca-uav and lewis-uav, the
registered images' mean says about 0.4 times it, the every-image mean 1.6 and 0.8 times it.
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

GPS_SLACK: float = 1.5
"""A geometry is trusted where its images' median error is under the nearest-image floor, or
under this many times the placed cameras' RMS distance from their GPS tags (the noise of the
check's own yardstick) where that is larger, ..."""

MAX_SLACK_M: float = 3.0
"""... though never above this (m) for that reason."""

SIGMA_FLOOR: float = 2.0
"""Least standard deviation (m) a registration is fused with."""


def trusted(figures: dict, gps_rms: float) -> bool:
    """Whether a map's self-check figures (:func:`self_check`) earn its geometry trust: it
    registers at least :data:`MIN_REGISTERED` of its images, and their median error is under
    the nearest-image floor or, where larger, :data:`GPS_SLACK` times the cameras' GPS RMS
    (at most :data:`MAX_SLACK_M`).

    The images' own GPS tags are the yardstick, so the check cannot measure below their
    noise: a dense map (the robot world's images lie 0.6 m apart; its GPS tags are 0.8 m
    RMS off) is judged against that noise."""
    if figures["registered"] < MIN_REGISTERED or figures.get("median_m") is None:
        return False
    slack = min(GPS_SLACK * gps_rms, MAX_SLACK_M) if math.isfinite(gps_rms) else 0.0
    return bool(figures["median_m"] < max(figures["floor_median_m"], slack))


def self_check(data: MapData, geometry: MapGeometry, *, seed: int = 0) -> MapGeometry | None:
    """Localise the map's images against the rest of it; ``geometry`` with its figures
    (``geometry.self_check``), or None where it does no better than the nearest image.

    The figures: ``images`` checked, ``registered`` share, ``mean_m``, ``median_m`` and
    ``within_5m`` of the registered ones' distance to their GPS, ``floor_mean_m`` and
    ``floor_median_m`` (each checked image's distance to its nearest other map image),
    ``sigma_m`` (the standard deviation registrations are fused with) and ``trusted``, all
    over the placed images; and ``every_image_mean_m``, ``every_image_median_m`` and
    ``every_image_within_5m`` over a spread sample of every map image, placed or not
    (:func:`_localise_own`, an image no pose reaches counted at its floor). A map of several
    flights adds ``flights``: per flight (``flight``, numbered in time order; ``name`` where
    the flight was named), its checked ``images``, ``registered`` share and their
    ``mean_m``, ``median_m`` and ``within_5m``.
    """
    positions = np.asarray(data.positions)
    placed = np.flatnonzero(geometry.reconstructed)
    n = len(positions)
    k = min(NEIGHBOURS, n - 1)
    if len(placed) == 0 or k < 1:
        geometry.self_check = {"images": 0, "registered": 0.0, "floor_mean_m": math.nan,
                               "floor_median_m": math.nan, "trusted": False}
        return None
    sample = placed[np.linspace(0, len(placed) - 1, min(SAMPLE, len(placed))).round()
                    .astype(np.int64)]
    sample = np.unique(sample)
    previous, data.geometry = data.geometry, geometry
    try:
        checked = {i: _localise_own(data, i, k) for i in sample.tolist()}
        everyone = np.unique(np.linspace(0, n - 1, min(SAMPLE, n)).round().astype(np.int64))
        for i in everyone.tolist():
            if i not in checked:
                checked[i] = _localise_own(data, i, k)
    finally:
        data.geometry = previous
    errors = [checked[i][0] for i in sample.tolist() if checked[i][0] is not None]
    floors = [checked[i][1] for i in sample.tolist()]
    every = np.array([checked[i][1] if checked[i][0] is None else checked[i][0]
                      for i in everyone.tolist()])
    errors_a, floors_a = np.asarray(errors), np.asarray(floors)
    figures = {"images": len(sample), "registered": len(errors) / len(sample),
               "floor_mean_m": float(floors_a.mean()),
               "floor_median_m": float(np.median(floors_a))}
    if len(errors_a):
        figures.update(mean_m=float(errors_a.mean()), median_m=float(np.median(errors_a)),
                       within_5m=float(np.mean(errors_a <= 5.0)))
    figures.update(every_image_mean_m=float(every.mean()),
                   every_image_median_m=float(np.median(every)),
                   every_image_within_5m=float(np.mean(every <= 5.0)))
    flights = _per_flight(data, sample.tolist(), checked)
    if flights:
        figures["flights"] = flights
    figures["trusted"] = ok = trusted(figures, geometry.gps_rms)
    figures["sigma_m"] = (max(SIGMA_FLOOR, 1.25 * figures["median_m"]) if len(errors_a)
                          else math.nan)
    geometry.self_check = figures
    return geometry if ok else None



def _per_flight(data: MapData, sample: list[int],
                checked: dict[int, tuple[float | None, float]]) -> list[dict]:
    """The registered figures of each flight of a map of several
    (:func:`workers.core.flights.flight_labels`); none for a map of one flight."""
    labels = data.flight_labels()
    found = sorted({int(labels[i]) for i in sample if labels[i] >= 0})
    if len(found) < 2:
        return []
    out = []
    for flight in found:
        mine = [i for i in sample if labels[i] == flight]
        errors = np.array([checked[i][0] for i in mine if checked[i][0] is not None])
        entry = {"flight": flight, "images": len(mine),
                 "registered": len(errors) / len(mine)}
        named = {data.flights[i] for i in mine} if data.flights is not None else {None}
        if len(named) == 1 and None not in named:
            entry["name"] = named.pop()
        if len(errors):
            entry.update(mean_m=float(errors.mean()), median_m=float(np.median(errors)),
                         within_5m=float(np.mean(errors <= 5.0)))
        out.append(entry)
    return out


def _localise_own(data: MapData, i: int, k: int) -> tuple[float | None, float]:
    """Map image ``i`` localised against its ``k`` nearest other images (the map's geometry
    set on ``data``): its distance (m) from its GPS where a pose registers (None where not),
    and its distance from the nearest of those images (the floor)."""
    positions = np.asarray(data.positions)
    _, near = data.tree.query(positions[i], k=k + 1)
    others = np.array([j for j in np.atleast_1d(near).tolist() if j != i][:k])
    floor = float(np.min(np.hypot(*(positions[others] - positions[i]).T)))
    fix = refine_sift(data.sift(i), data, others, np.ones(len(others)),
                      frame_shape=(WORK_SIZE[1], WORK_SIZE[0]))
    if fix is None or fix.kind != "registered":
        return None, floor
    return float(np.hypot(*(fix.xy - positions[i]))), floor
