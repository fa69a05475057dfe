"""A map that measures itself: its images localised against the rest of it, on a synthetic
survey with exact keypoints, with its right geometry and with wrong ones."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from tests.core.geometry.scene import F_TRUE, survey
from vloc.workers.core import selfcheck
from vloc.workers.core.geo import GeoOrigin
from vloc.workers.core.image import WORK_SIZE
from vloc.workers.core.localisers.refine import refine_sift
from vloc.workers.core.mapbuild import map_geometry
from vloc.workers.core.mapdata import MapData
from vloc.workers.core.selfcheck import self_check, trusted
from vloc.workers.core.sift import SiftFeatures


def _map(s):
    return MapData.from_parts(origin=GeoOrigin(41.03, -83.30, 260.0),
                              names=[f"m{i}" for i in range(len(s))], positions=s.positions,
                              altitudes=s.altitudes, global_features={},
                              sift=[SiftFeatures(k, d) for k, d in
                                    zip(s.keypoints, s.image_descriptors, strict=True)])


@pytest.fixture(scope="module")
def surveyed():
    s = survey(np.random.default_rng(31), rows=3, cols=4)
    data = _map(s)
    geo = map_geometry(data, focal_px=F_TRUE)  # checked once already: trusted
    assert geo is not None and geo.self_check["trusted"]
    return s, data, geo


def _moved(geo, shift=(0.0, 0.0, 0.0), scale=1.0):
    """The geometry with its keypoints' 3-D points moved: ``scale`` about their centroid,
    then ``shift``."""
    points = np.asarray(geo.points["sift"], np.float64)
    centroid = np.nanmean(points, axis=0)
    moved = (centroid + scale * (points - centroid) + shift).astype(np.float32)
    return replace(geo, points={"sift": moved}, self_check={})


def _per_image(data, geo):
    """The slow obvious reference: each map image localised by refine_sift against its four
    GPS-nearest others: its error against its GPS (None where no pose registers), and its
    distance to its nearest other image."""
    positions = np.asarray(data.positions)
    out = []
    data.geometry = geo
    try:
        for i in range(len(data)):
            d = np.linalg.norm(positions - positions[i], axis=1)
            d[i] = np.inf
            others = np.argsort(d, kind="stable")[:4]
            fix = refine_sift(data.sift(i), data, others, np.ones(4),
                              frame_shape=(WORK_SIZE[1], WORK_SIZE[0]))
            registered = fix is not None and fix.kind == "registered"
            out.append((math.dist(fix.xy, positions[i]) if registered else None,
                        d[others[0]]))
    finally:
        data.geometry = None
    return out


def _reference(data, geo):
    """The registered images' errors and every image's nearest other image."""
    out = _per_image(data, geo)
    return (np.array([e for e, _ in out if e is not None]),
            np.array([floor for _, floor in out]))


def _every_image(data, geo):
    """Every image's error, or its nearest-image distance where no pose registers."""
    return np.array([floor if e is None else e for e, floor in _per_image(data, geo)])


def test_self_check_accepts_the_right_geometry_with_its_figures(surveyed):
    s, data, geo = surveyed
    before = dict(geo.self_check)
    assert data.geometry is None
    out = self_check(data, geo)
    assert out is geo and data.geometry is None  # the map's own geometry is left alone
    figures = geo.self_check
    assert figures == before  # the same figures as at build: the check is deterministic
    errors, floors = _reference(data, replace(geo, self_check={}))
    assert figures["images"] == len(s) and len(errors) >= 0.8 * len(s)
    assert figures["registered"] == pytest.approx(len(errors) / len(s))
    assert figures["mean_m"] == pytest.approx(errors.mean())
    assert figures["median_m"] == pytest.approx(np.median(errors))
    assert figures["within_5m"] == pytest.approx(np.mean(errors <= 5.0))
    assert figures["floor_mean_m"] == pytest.approx(floors.mean())
    assert figures["floor_median_m"] == pytest.approx(np.median(floors))
    # exact keypoints: the map's own images come back to within a metre, where the nearest
    # other image is 18 m away
    assert figures["median_m"] < 1.0 < 15.0 < figures["floor_median_m"]
    assert figures["trusted"] is True
    assert figures["sigma_m"] == max(selfcheck.SIGMA_FLOOR, 1.25 * figures["median_m"]) == 2.0
    assert geo.base_sigma == 2.0
    # the whole map's figures: here every image is placed, so they count the registered
    # errors and, for an image no pose reaches, its nearest-image distance
    every = _every_image(data, replace(geo, self_check={}))
    assert figures["every_image_mean_m"] == pytest.approx(every.mean())
    assert figures["every_image_median_m"] == pytest.approx(np.median(every))
    assert figures["every_image_within_5m"] == pytest.approx(np.mean(every <= 5.0))
    assert figures["every_image_mean_m"] >= figures["mean_m"]


def test_a_map_of_two_flights_gets_the_figures_of_each(surveyed):
    """The survey's first five images flown in the morning, the rest in the afternoon: the
    check reports each flight's registered figures, which make up the map's."""
    s, data, geo = surveyed
    hour = 3600.0
    times = np.where(np.arange(len(s)) < 5, 8 * hour, 15 * hour) + np.arange(len(s))
    flown = replace(data, captured_at=times)
    figures = self_check(flown, replace(geo, self_check={})).self_check
    per_image = _per_image(data, replace(geo, self_check={}))
    flights = figures["flights"]
    assert [(f["flight"], f["images"]) for f in flights] == [(0, 5), (1, len(s) - 5)]
    for f, part in zip(flights, (per_image[:5], per_image[5:]), strict=True):
        errors = np.array([e for e, _ in part if e is not None])
        assert f["registered"] == pytest.approx(len(errors) / len(part))
        assert f["mean_m"] == pytest.approx(errors.mean())
        assert f["median_m"] == pytest.approx(np.median(errors))
        assert f["within_5m"] == pytest.approx(np.mean(errors <= 5.0))
    # one flight: no per-flight figures
    assert "flights" not in geo.self_check


def test_flights_named_at_upload_get_their_figures_and_names(surveyed):
    """The same images flown in one run but uploaded as two named passes (the odd images
    "dusk", the even "noon"): each named flight gets its figures and its name."""
    s, data, geo = surveyed
    named = replace(data, captured_at=np.arange(len(s)) * 4.0,
                    flights=tuple("dusk" if i % 2 else "noon" for i in range(len(s))))
    figures = self_check(named, replace(geo, self_check={})).self_check
    per_image = _per_image(data, replace(geo, self_check={}))
    flights = figures["flights"]
    assert [(f["flight"], f["name"], f["images"]) for f in flights] == \
        [(0, "noon", (len(s) + 1) // 2), (1, "dusk", len(s) // 2)]
    for f, part in zip(flights, (per_image[0::2], per_image[1::2]), strict=True):
        errors = np.array([e for e, _ in part if e is not None])
        assert f["mean_m"] == pytest.approx(errors.mean())
    # the same run unnamed is one flight
    one = self_check(replace(data, captured_at=np.arange(len(s)) * 4.0),
                     replace(geo, self_check={})).self_check
    assert "flights" not in one


@pytest.mark.parametrize("shift", [(30.0, 0.0, 0.0), (0.0, -25.0, 10.0)],
                         ids=["30 m east", "25 m south, 10 m up"])
def test_self_check_refuses_a_geometry_that_places_the_images_wrong(surveyed, shift):
    # the same cameras and the same points, moved: consistent, and wrong by more than the
    # nearest image (18 m)
    s, data, geo = surveyed
    wrong = _moved(geo, shift)
    assert self_check(data, wrong) is None
    figures = wrong.self_check
    assert figures["trusted"] is False and figures["registered"] == 1.0
    assert figures["median_m"] == pytest.approx(np.hypot(*shift[:2]), abs=2.0)
    assert figures["median_m"] > figures["floor_median_m"]
    assert figures["sigma_m"] == pytest.approx(1.25 * figures["median_m"])
    # moved by less than the floor, the same points are still better than the nearest
    # image: kept, with their error as the registrations' sigma
    small = _moved(geo, (4.0, 0.0, 0.0))
    assert self_check(data, small) is small
    assert small.self_check["median_m"] == pytest.approx(4.0, abs=1.0)
    assert small.self_check["sigma_m"] == pytest.approx(1.25 * small.self_check["median_m"])
    assert small.base_sigma == small.self_check["sigma_m"]


@pytest.mark.parametrize("scale", [2.5, 0.5])
def test_self_check_refuses_a_geometry_of_the_wrong_size(surveyed, scale):
    # points spread 2.5 times as far put the frames' cameras at altitudes the map's rule
    # out; half as far, few register
    s, data, geo = surveyed
    wrong = _moved(geo, scale=scale)
    assert self_check(data, wrong) is None
    figures = wrong.self_check
    assert figures["trusted"] is False
    assert figures["registered"] < selfcheck.MIN_REGISTERED


def test_self_check_refuses_a_geometry_that_registers_too_few(surveyed):
    s, data, geo = surveyed
    unknown = _moved(geo)
    unknown.points["sift"][:] = np.nan
    assert self_check(data, unknown) is None
    figures = unknown.self_check
    assert figures["registered"] == 0.0 and figures["trusted"] is False
    assert "median_m" not in figures and math.isnan(figures["sigma_m"])
    # nothing registers: the whole map is only as good as its images' spacing
    _, floors = _reference(data, replace(unknown, self_check={}))
    assert figures["every_image_mean_m"] == pytest.approx(floors.mean())
    assert figures["every_image_median_m"] == pytest.approx(np.median(floors))
    assert unknown.base_sigma == 2.0


def test_self_check_samples_a_large_map_evenly(surveyed, monkeypatch):
    s, data, geo = surveyed
    monkeypatch.setattr(selfcheck, "SAMPLE", 4)
    checked = []
    real = selfcheck.refine_sift
    monkeypatch.setattr(selfcheck, "refine_sift",
                        lambda query, *a, **k: checked.append(query) or real(query, *a, **k))
    out = self_check(data, _moved(geo))
    assert out is not None and out.self_check["images"] == 4
    # images 0, 4, 7 and 11 of the twelve (rounded from 0, 3.67, 7.33, 11)
    want = [data.sift(i).keypoints for i in (0, 4, 7, 11)]
    assert len(checked) == 4
    for got, k in zip(checked, want, strict=True):
        np.testing.assert_array_equal(got.keypoints, k)


def test_self_check_of_a_senseless_geometry_or_one_without_cameras_is_none(surveyed):
    s, data, geo = surveyed
    # four images checked against their three others: cameras that see nothing of them
    four = _map(survey(np.random.default_rng(32), rows=1, cols=4))
    rotations = np.stack([np.eye(3)] * 4)
    small = replace(geo, rotations=rotations, centres=np.zeros((4, 3)), self_check={})
    assert self_check(four, small) is None
    assert small.self_check["images"] == 4 and small.self_check["registered"] == 0.0
    assert small.self_check["trusted"] is False
    nothing = replace(geo, centres=np.full_like(geo.centres, np.nan), self_check={})
    assert self_check(data, nothing) is None
    assert (nothing.self_check["images"], nothing.self_check["trusted"]) == (0, False)


@pytest.mark.parametrize(("figures", "gps_rms", "want"), [
    (dict(registered=0.9, median_m=2.0, floor_median_m=28.0), 3.0, True),
    (dict(registered=0.9, median_m=30.0, floor_median_m=28.0), 3.0, False),   # no better
    (dict(registered=0.3, median_m=2.0, floor_median_m=28.0), 3.0, False),    # too few
    (dict(registered=0.9, median_m=None, floor_median_m=28.0), 3.0, False),
    # a dense map: 0.7 m against a 0.6 m floor, inside its tags' own noise (1.5 x 0.8 m)
    (dict(registered=1.0, median_m=0.7, floor_median_m=0.6), 0.8, True),
    (dict(registered=1.0, median_m=1.3, floor_median_m=0.6), 0.8, False),
    # the slack stops at 3 m however loose the tags
    (dict(registered=1.0, median_m=3.5, floor_median_m=0.6), 10.0, False),
    (dict(registered=1.0, median_m=2.9, floor_median_m=0.6), 10.0, True),
    (dict(registered=1.0, median_m=0.7, floor_median_m=0.6), float("nan"), False),
])
def test_trust_known_answers(figures, gps_rms, want):
    assert trusted(figures, gps_rms) is want
