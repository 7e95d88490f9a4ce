"""The autopilot's parameters: declared once (filters.params), ArduPlane names, set by name."""
from __future__ import annotations

import dataclasses
import math

import pytest

from filters.params import ParamError, checks, docs
from vehicles.autopilot.config import (ARDUPILOT_NAMES, PARAM_NAMES, PARAM_UNITS, AutopilotConfig, param_rows,
                                       with_param)
from vehicles.mavlink.params import ParamSpec


def test_every_field_is_declared_named_and_united():
    fields = [f.name for f in dataclasses.fields(AutopilotConfig)]
    assert list(checks(AutopilotConfig)) == fields and all(docs(AutopilotConfig).values())
    assert list(PARAM_NAMES) == fields and set(PARAM_UNITS) == set(fields)
    for name, value, unit, doc, ours in param_rows(AutopilotConfig()):
        ParamSpec(name, value, doc=f"{doc} [{unit}]")  # the MAVLink layer's own name rules
        assert ours == (name in ARDUPILOT_NAMES) == (not name.startswith("SF_"))
    for n in ("WP_RADIUS", "WP_LOITER_RAD", "RTL_ALTITUDE", "AIRSPEED_CRUISE", "AIRSPEED_MIN", "AIRSPEED_MAX",
              "TKOFF_ALT", "BATT_CAPACITY"):
        assert n in ARDUPILOT_NAMES


def test_with_param_checks_values_and_combinations():
    c = AutopilotConfig()
    assert with_param(c, "WP_RADIUS", 50).wp_radius_m == 50.0 and c.wp_radius_m == 200.0
    assert with_param(c, "RTL_ALTITUDE", -1).rtl_altitude_m == -1.0
    for name, v in (("WP_RADIUS", math.nan), ("WP_RADIUS", -1.0), ("AIRSPEED_MIN", 120.0), ("NO_SUCH", 1.0),
                    ("RTL_ALTITUDE", -2.0), ("TKOFF_ALT", "x")):
        with pytest.raises(ParamError) as e:
            with_param(c, name, v)
        assert str(e.value).startswith(name) and "\n" not in str(e.value)
