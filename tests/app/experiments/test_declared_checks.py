"""The experiments' scenario / plan dataclasses declare their checks (sitl.params): a bad value is
one line naming the field; every field carries a doc; the windows and the fault levels keep their
stored types (tuples of floats)."""
import dataclasses
import math

import pytest

from sitl.app.experiments import network_faults as fx
from sitl.app.experiments import sonde
from sitl.app.experiments.ekf_vs_ukf import EkfVsUkfScenario
from sitl.params import ParamError, docs


@pytest.mark.parametrize("cls, kw, field", [
    (sonde.SondeScenario, {"dt_s": 0.0}, "dt_s"),
    (sonde.SondeScenario, {"filter": "kalman"}, "filter"),
    (sonde.SondeScenario, {"radar_loss_s": (330.0, 30.0)}, "radar_loss_s"),
    (sonde.SondeScenario, {"gnss_outage_s": (3600.0, math.inf)}, "gnss_outage_s"),
    (sonde.SondeScenario, {"az_outlier_s": (1.0,)}, "az_outlier_s"),
    (sonde.SondeScenario, {"acquire_s": 7200.0}, "acquire_s"),
    (sonde.SondeScenario, {"white_baseline": 1}, "white_baseline"),
    (EkfVsUkfScenario, {"steps": 0}, "steps"),
    (EkfVsUkfScenario, {"dt_s": math.nan}, "dt_s"),
    (EkfVsUkfScenario, {"lat_deg": 90.5}, "lat_deg"),
    (fx.Plan, {"loss": (0.0,)}, "loss"),
    (fx.Plan, {"delay_s": (61.0,)}, "delay_s"),
    (fx.Plan, {"burst_len": 0.5}, "burst_len"),
    (fx.Plan, {"jitter_frac": 1.5}, "jitter_frac"),
    (fx.Plan, {"recovery_factor": 1.0}, "recovery_factor"),
    (fx.Setup, {"name": "radar", "duration_s": 300.0, "settle_s": 100.0, "partition_at_s": 150.0}, "name"),
    (fx.Setup, {"name": "beacon", "duration_s": 0.0, "settle_s": 100.0, "partition_at_s": 150.0}, "duration_s"),
])
def test_a_bad_value_is_one_line_naming_the_field(cls, kw, field):
    with pytest.raises(ParamError) as e:
        cls(**kw)
    assert e.value.key == field and str(e.value).startswith(field + ": ") and "\n" not in str(e.value)


@pytest.mark.parametrize("cls", [sonde.SondeScenario, EkfVsUkfScenario, fx.Plan, fx.Setup])
def test_every_field_is_declared_with_a_doc(cls):
    assert set(docs(cls)) == {f.name for f in dataclasses.fields(cls)}
    assert all(d.strip() for d in docs(cls).values())


def test_windows_and_levels_are_tuples_of_floats():
    scn = sonde.SondeScenario(radar_loss_s=[30, 330], relay_step_s=(1200, math.inf))
    assert scn.radar_loss_s == (30.0, 330.0) and type(scn.radar_loss_s) is tuple
    assert scn.relay_step_s == (1200.0, math.inf)  # a fault may last to the end of the flight
    plan = fx.Plan(loss=[0.2], partition_s=(30,))
    assert plan.loss == (0.2,) and plan.partition_s == (30.0,) and all(type(v) is float for v in plan.partition_s)
    hash(scn), hash(plan)  # still hashable (frozen, tuples)


def test_setup_check_names_the_scenario():
    with pytest.raises(ValueError, match=r"^beacon: duration 80 s is too short"):
        fx.Setup("beacon", 80.0, 20.0, 40.0, margin_s=20.0).check(fx.DEFAULT_PLAN)
