"""A map's flights from its capture times: known answers."""

from __future__ import annotations

import numpy as np

from vloc.workers.core.flights import FLIGHT_GAP_S, flight_labels


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
