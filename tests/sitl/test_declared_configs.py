"""The world's configuration dataclasses declare their checks (filters.params): every field
carries a doc, and a bad value is a one-line ParamError naming the field."""
import dataclasses
import math

import numpy as np
import pytest

from filters.params import ParamError, docs
from sitl.gnss.clock import ClockModel
from sitl.gnss.ranging import finite_vec3
from sitl.gnss.receiver import ReceiverConfig
from sitl.measfault import Fault
from sitl.netfault.spec import FaultSpec, FaultSpecError
from sitl.radio.beacon_link import BeaconLinkConfig
from sitl.radio.radar import RadarParams
from sitl.radio.relay import RelayErrorBudget, RelayParams

CLASSES = [BeaconLinkConfig, RadarParams, RelayParams, RelayErrorBudget, ClockModel, ReceiverConfig, FaultSpec, Fault]


@pytest.mark.parametrize("cls", CLASSES, ids=lambda c: c.__name__)
def test_every_field_is_declared_with_a_doc(cls):
    d = docs(cls)
    assert list(d) == [f.name for f in dataclasses.fields(cls)]
    assert all(len(text) > 10 for text in d.values())


STEP = dict(kind="step", channel=0, t_start_s=0.0)
BAD = [  # (class, other arguments, field, bad value)
    (BeaconLinkConfig, {}, "dt_s", 0.0),
    (BeaconLinkConfig, {}, "psd_range_rate_m2_s", -1e-3),
    (RadarParams, {}, "loss_ang_rate_ref_rad_s", 0.0),
    (RadarParams, {}, "el_mask_rad", math.pi / 2),
    (RelayParams, {}, "osc_phase_psd_rad2_s", -1.0),
    (RelayParams, {}, "ground_el_mask_rad", -2.0),
    (RelayErrorBudget, {}, "multipath_el0_deg", 0.0),
    (RelayErrorBudget, {}, "sisre_gps_m", math.inf),
    (ClockModel, {}, "psd_1_s", "x"),
    (ReceiverConfig, {}, "ambiguity_max_cycles", 2.5),
    (ReceiverConfig, {}, "iono_ref_hz", 0.0),
    (ReceiverConfig, {}, "el_mask_rad", math.pi / 2),
    (Fault, STEP, "channel", True),
    (Fault, STEP, "trial", -1),
    (Fault, STEP, "rate", math.nan),
    (Fault, dict(kind="outlier", channel=0, t_start_s=0.0), "dof", 0.0),
]


@pytest.mark.parametrize("cls, kw, name, bad", BAD, ids=[f"{c.__name__}.{n}" for c, _, n, _ in BAD])
def test_a_bad_value_is_a_one_line_error_naming_the_field(cls, kw, name, bad):
    with pytest.raises(ParamError) as ei:
        cls(**{**kw, name: bad})
    msg = str(ei.value)
    assert ei.value.key == name and msg.startswith(f"{name}: expected") and "\n" not in msg


def test_fault_spec_errors_stay_fault_spec_errors():
    with pytest.raises(FaultSpecError) as ei:
        FaultSpec(jitter_s=-1.0)
    assert str(ei.value) == "fault spec: jitter_s: expected a finite number >= 0, got -1.0"
    assert FaultSpec(ge=[0.1, 0.2, 1.0, 0.0]).ge == (0.1, 0.2, 1.0, 0.0)  # stored as a tuple of floats


def test_numbers_are_stored_as_floats():
    assert type(RadarParams(max_range_m=100_000).max_range_m) is float
    assert type(ReceiverConfig(slip_cycles_max=3).slip_cycles_max) is int
    assert RadarParams(loss_schedule=[[1, 2]]).loss_schedule == ((1.0, 2.0),)


def test_finite_vec3_takes_any_batch_without_a_copy():
    a = np.zeros((2, 4, 3))
    assert finite_vec3("p", a) is a
    for bad, what in ((np.zeros((2, 2)), "shape (2, 2)"), ([0.0, np.nan, 0.0], "non-finite"), ("abc", "a str")):
        with pytest.raises(ParamError) as ei:
            finite_vec3("rx_pos_ecef_m", bad)
        assert what in str(ei.value) and str(ei.value).startswith("rx_pos_ecef_m: expected a finite (..., 3) array")
