"""The ground station's configurations (SondeTrackerParams, LocatorConfig) declare their checks
(filters.params): every field carries a doc, and a bad value is a one-line ParamError naming it."""
import dataclasses
import math

import pytest

from filters.params import ParamError, docs
from ground_station.beacon import LocatorConfig
from ground_station.sonde import SondeTrackerParams


@pytest.mark.parametrize("cls", [SondeTrackerParams, LocatorConfig], ids=lambda c: c.__name__)
def test_every_field_is_declared_with_a_doc(cls):
    d = docs(cls)
    assert list(d) == [f.name for f in dataclasses.fields(cls)]
    assert all(len(text) > 10 for text in d.values())


BAD = [
    (SondeTrackerParams, "label", "bad id"),
    (SondeTrackerParams, "backend", "cuda"),
    (SondeTrackerParams, "bias_slots", 0),
    (SondeTrackerParams, "integrity_sat_channels", True),
    (SondeTrackerParams, "relay_errors", "white"),
    (SondeTrackerParams, "landing", "yes"),
    (SondeTrackerParams, "radar_gamma_1_s", (0.1, 0.1)),
    (SondeTrackerParams, "integrity_common_fraction", 1.5),
    (LocatorConfig, "backend", "cuda"),
    (LocatorConfig, "second_order_r", "yes"),
    (LocatorConfig, "init_height_sigma_m", math.nan),
    (LocatorConfig, "search_height_m", (5000.0, -500.0)),
    (LocatorConfig, "search_height_m", (0.0, math.inf)),
    (LocatorConfig, "search_height_m", (0.0,)),
    (LocatorConfig, "axis_ratio", 1.5),
    (LocatorConfig, "gate_prob", 0.0),
    (LocatorConfig, "init_epochs", 2.5),
]


@pytest.mark.parametrize("cls, name, bad", BAD, ids=[f"{c.__name__}.{n}" for c, n, _ in BAD])
def test_a_bad_value_is_a_one_line_error_naming_the_field(cls, name, bad):
    with pytest.raises(ParamError) as ei:
        cls(**{name: bad})
    msg = str(ei.value)
    assert ei.value.key == name and "\n" not in msg


def test_tuples_stay_tuples_of_floats():
    p = SondeTrackerParams(radar_sigma=[10, 0.001, 0.001], burst_alt_range_m=[20_000, 30_000])
    assert p.radar_sigma == (10.0, 0.001, 0.001) and type(p.radar_sigma) is tuple
    assert p.burst_alt_range_m == (20_000.0, 30_000.0) and type(p.burst_alt_range_m) is tuple
    assert LocatorConfig(init_height_sigma_m=math.inf).init_height_sigma_m == math.inf
    assert LocatorConfig(search_height_m=[-500, 5000]).search_height_m == (-500.0, 5000.0)
