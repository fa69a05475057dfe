"""A map's flights from its capture times: known answers."""

from __future__ import annotations

import numpy as np

from vloc.workers.core.flights import FLIGHT_GAP_S, flight_labels, flight_spacing
from vloc.workers.core.geometry import tie_pairs, tie_reach


def test_flights_split_at_long_pauses_and_number_in_time_order():
    hour = 3600.0
    # two flights given out of order, a battery change (10 min) inside the first, and an
    # untimed image
    t = [5 * hour + 2, 0.0, 5 * hour, 600.0 + 60, np.nan, 600.0, 5 * hour + 1]
    assert flight_labels(t).tolist() == [1, 0, 1, 0, -1, 0, 1]
    assert flight_labels(t, gap_s=300.0).tolist() == [2, 0, 2, 1, -1, 1, 2]


def test_a_pause_of_exactly_the_gap_stays_in_the_flight_and_untimed_maps_have_none():
    assert flight_labels([0.0, FLIGHT_GAP_S, 2 * FLIGHT_GAP_S + 1]).tolist() == [0, 0, 1]
    assert flight_labels([np.nan, np.nan]).tolist() == [-1, -1]
    assert flight_labels([]).tolist() == []


def _reference_spacing(xy, labels):
    """The slow obvious reference: per image, the distance to the nearest other image of
    its flight (untimed ones one flight of their own)."""
    out = []
    for i in range(len(xy)):
        same = [j for j in range(len(xy)) if j != i and labels[j] == labels[i]]
        if same:
            out.append(min(float(np.hypot(*(xy[j] - xy[i]))) for j in same))
    return float(np.median(out))


def test_a_second_flight_over_the_same_waypoints_leaves_the_spacing_as_it_was():
    """A line survey every 10 m flown twice, the second flight 6 hours later and 0.5 m
    beside the first (GPS): over every image the spacing would be 0.5 m; per flight it is
    the survey's 10 m, as for the first flight alone."""
    line = np.column_stack([np.arange(0.0, 200.0, 10.0), np.zeros(20)])
    xy = np.concatenate([line, line + [0.0, 0.5]])
    t = np.concatenate([np.arange(20) * 4.0, 6 * 3600.0 + np.arange(20) * 4.0])
    assert flight_spacing(xy, t) == 10.0 == flight_spacing(line, t[:20])
    assert flight_spacing(xy) == 0.5  # without capture times the flights are one
    rng = np.random.default_rng(5)
    xy = rng.uniform(0, 300, (60, 2))
    t = np.where(np.arange(60) < 25, 0.0, 9 * 3600.0) + rng.uniform(0, 600, 60)
    t[[3, 40, 41]] = np.nan
    assert flight_spacing(xy, t) == _reference_spacing(xy, flight_labels(t))
    assert flight_spacing(xy[:1]) == 1.0


def test_tie_pairs_of_two_flights_reach_as_far_as_those_of_one():
    """The tie points of a survey flown twice are matched within the reach of one flight
    (six spacings), across the flights too; without times the second flight's images 0.5 m
    away would shrink the reach to 3 m and leave each image paired with its twin only."""
    grid = np.array([[x, y] for y in (0.0, 15.0, 30.0) for x in np.arange(0.0, 150.0, 10.0)])
    xy = np.concatenate([grid, grid + [0.5, 0.0]])
    n = len(grid)
    t = np.concatenate([np.arange(n) * 4.0, 6 * 3600.0 + np.arange(n) * 4.0])
    one = tie_pairs(grid, t[:n])
    assert tie_reach(xy, t) == tie_reach(grid, t[:n]) == 60.0
    both = tie_pairs(xy, t)
    across = [(a, b) for a, b in both if (a < n) != (b < n)]
    assert len(both) > len(one) and len(across) >= n
    blind = tie_pairs(xy)
    assert tie_reach(xy) == 3.0 and all(b - a == n for a, b in blind)


def test_named_flights_hold_their_images_whatever_their_times():
    """Two passes flown one after the other (seconds apart: one flight by time) and named
    "pass 1" / "pass 2"; an unnamed flight hours later; a named image without a time; an
    unnamed untimed image. Named flights number by their first capture like the others."""
    hour = 3600.0
    t = [10.0, 20.0, 30.0, 40.0, 3 * hour, 3 * hour + 5, np.nan, np.nan, 0.0]
    names = ["pass 2", "pass 2", "pass 1", "pass 1", None, None, "pass 1", None, "pass 1"]
    assert flight_labels(t, names).tolist() == [1, 1, 0, 0, 2, 2, 0, -1, 0]
    # a flight of named images with no time at all comes after the timed ones
    assert flight_labels([np.nan, 5.0, np.nan], ["late", None, "late"]).tolist() == [1, 0, 1]
    # naming no image changes nothing
    assert flight_labels(t, [None] * len(t)).tolist() == flight_labels(t).tolist()


def test_one_name_spans_a_pause_and_two_names_split_a_run():
    hour = 3600.0
    assert flight_labels([0.0, 5 * hour], ["dawn", "dawn"]).tolist() == [0, 0]
    assert flight_labels([0.0, 1.0, 2.0], ["a", "b", "a"]).tolist() == [0, 1, 0]


def test_flights_must_name_every_image_or_none():
    import pytest

    with pytest.raises(ValueError, match="one entry per image"):
        flight_labels([0.0, 1.0], ["a"])


def test_named_passes_flown_back_to_back_keep_their_own_spacing():
    """Seneca's two passes are 73 s apart at most: by time they are one flight, and the
    second pass's twin images 0.5 m away set the spacing. Named, each pass keeps the
    survey's 10 m, as the slow reference over the named flights says."""
    line = np.column_stack([np.arange(0.0, 200.0, 10.0), np.zeros(20)])
    xy = np.concatenate([line, line + [0.0, 0.5]])
    t = np.arange(40) * 4.0
    names = ["pass 1"] * 20 + ["pass 2"] * 20
    assert flight_spacing(xy, t) == 0.5
    assert flight_spacing(xy, t, names) == 10.0 == _reference_spacing(
        xy, flight_labels(t, names))
    assert flight_spacing(xy, None, names) == 10.0
    assert tie_reach(xy, t, names) == 60.0 and tie_reach(xy, t) == 3.0
