"""A device's per-frame metadata: validation, and what the filter makes of it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from vloc.workers.core.metadata import FrameMetadata


@pytest.mark.parametrize(("fields", "message"), [
    ({"heading_deg": math.nan}, "heading_deg must be a finite number"),
    ({"heading_deg": 360.0}, "heading_deg must be in [0, 360)"),
    ({"heading_deg": -1.0}, "heading_deg must be in [0, 360)"),
    ({"heading_deg": 10.0, "heading_accuracy_deg": 0.0}, "heading_accuracy_deg must be positive"),
    ({"heading_accuracy_deg": 5.0}, "heading_accuracy_deg needs heading_deg"),
    ({"gps_lat": 41.0}, "gps_lat and gps_lon come together"),
    ({"gps_lat": 91.0, "gps_lon": 0.0}, "gps_lat must be in [-90, 90]"),
    ({"gps_lat": 41.0, "gps_lon": -83.0, "gps_accuracy_m": -3.0},
     "gps_accuracy_m must be positive"),
    ({"gps_accuracy_m": 3.0}, "gps_accuracy_m needs gps_lat and gps_lon"),
    ({"gps_lat": 41.0, "gps_lon": -83.0, "gps_accuracy_m": 1e308},
     "gps_accuracy_m must be in [0.01, 10000]"),
    ({"heading_deg": 10.0, "heading_accuracy_deg": 1e-300},
     "heading_accuracy_deg must be in [0.01, 180]"),
    ({"altitude_m": math.inf}, "altitude_m must be a finite number"),
    ({"altitude_m": 20_000.0}, "altitude_m must be in [-500, 10000]"),
    ({"velocity_east": 1.0}, "velocity_east and velocity_north come together"),
    ({"velocity_east": 200.0, "velocity_north": 0.0}, "velocity must be at most 150 m/s"),
])
def test_bad_metadata_is_refused_with_the_field(fields, message):
    with pytest.raises(ValueError, match=message.replace("[", r"\[").replace(")", r"\)")):
        FrameMetadata(**fields)


def test_round_trip_kinds_and_selection():
    m = FrameMetadata(heading_deg=90.0, gps_lat=41.0, gps_lon=-83.0, gps_accuracy_m=30.0,
                      altitude_m=280.0)
    assert m.kinds() == ("heading", "gps", "altitude")
    assert FrameMetadata.from_dict(m.to_dict()) == m
    assert FrameMetadata.from_dict({}) is None and FrameMetadata.from_dict(None) is None
    only = m.only({"gps"})
    assert only.kinds() == ("gps",) and only.gps_accuracy_m == 30.0
    with pytest.raises(ValueError, match="unknown metadata fields"):
        FrameMetadata.from_dict({"speed": 3})
    with pytest.raises(ValueError, match="unknown metadata kinds"):
        m.only({"compass"})
    assert np.isclose(m.to_dict()["heading_deg"], 90.0)
