"""The integrity and iono-tropo scenarios' declared checks (sitl.params): every field has a doc, a
bad value is a one-line ParamError naming the field, and the checks the core lacks (within, the
integrity scenario's (low, high) pairs) take and refuse what the hand-written checks did."""
from __future__ import annotations

import dataclasses

import pytest

from sitl.app.experiments.integrity import IntegrityScenario
from sitl.app.experiments.iono_tropo_filters import IonoTropoScenario
from sitl.params import ParamError, docs, number


@pytest.mark.parametrize("cls", [IntegrityScenario, IonoTropoScenario])
def test_every_field_is_declared_with_a_doc(cls):
    d = docs(cls)
    assert list(d) == [f.name for f in dataclasses.fields(cls)]
    assert all(len(text) > 10 for text in d.values())


@pytest.mark.parametrize("cls, kw, key", [
    (IntegrityScenario, {"duration_s": -1.0}, "duration_s"),
    (IntegrityScenario, {"el_mask_deg": 90.0}, "el_mask_deg"),
    (IntegrityScenario, {"systems": "RG"}, "systems"),
    (IntegrityScenario, {"faults": 1}, "faults"),
    (IntegrityScenario, {"step_sigma": (20.0, 5.0)}, "step_sigma"),
    (IntegrityScenario, {"step_sigma": (-1.0, 5.0)}, "step_sigma"),
    (IntegrityScenario, {"dropout_s": (0.0, 1.0)}, "dropout_s"),
    (IntegrityScenario, {"dropout_s": 5}, "dropout_s"),
    (IntegrityScenario, {"outlier_prob": 1.5}, "outlier_prob"),
    (IntegrityScenario, {"window": 2.0}, "window"),
    (IntegrityScenario, {"r_forget": 0.0}, "r_forget"),
    (IntegrityScenario, {"duration_s": 50.0}, "duration_s"),  # no room for the fault onsets
    (IntegrityScenario, {"el_mask_deg": 60.0}, "el_mask_deg"),  # too few satellites in view
    (IonoTropoScenario, {"sigma_pr_m": 0.0}, "sigma_pr_m"),
    (IonoTropoScenario, {"lat_deg": 90.0}, "lat_deg"),
    (IonoTropoScenario, {"h_m": 1e6}, "h_m"),
    (IonoTropoScenario, {"systems": "GG"}, "systems"),
    (IonoTropoScenario, {"adaptive_q": 1}, "adaptive_q"),
    (IonoTropoScenario, {"phase_max_sats": 1.0}, "phase_max_sats"),
    (IonoTropoScenario, {"cmc_window_s": 0.15, "duration_s": 10.0}, "cmc_window_s"),
    (IonoTropoScenario, {"dt_s": 2.0, "duration_s": 1.0}, "dt_s"),
])
def test_a_bad_value_is_one_line_naming_the_field(cls, kw, key):
    with pytest.raises(ParamError) as exc:
        cls(**kw)
    assert exc.value.key == key
    assert str(exc.value).startswith(f"{key}: ") and "\n" not in str(exc.value)


def test_what_the_checks_store():
    scn = IntegrityScenario(duration_s=100.0, step_sigma=[5, 20], outlier_prob=0, jump_sigma=float("inf"),
                            bias_alpha=None, huber_c=None)
    assert scn.step_sigma == (5.0, 20.0) and type(scn.step_sigma) is tuple  # hashable: a tuple of floats
    assert type(scn.outlier_prob) is float and scn.jump_sigma == float("inf")
    assert type(scn.window) is int and hash(scn) == hash(dataclasses.replace(scn))
    it = IonoTropoScenario(duration_s=1.0, el_mask_deg=10, systems="RG", phase_max_sats=2)
    assert type(it.el_mask_deg) is float and type(it.phase_max_sats) is int and it.systems == "RG"


def test_bounded_number_open_and_closed():
    closed, half = number(0, hi=1), number(5, hi=90, hi_open=True)
    assert closed("p", 0) == 0.0 and closed("p", 1) == 1.0
    assert half("m", 5) == 5.0 and half.parse("89.5") == 89.5
    for v in (1.5, -0.1, float("nan")):
        with pytest.raises(ParamError, match=r"^p: expected a number in \[0, 1\], got "):
            closed("p", v)
    for v in (90, 4.9, True, "10"):
        with pytest.raises(ParamError, match=r"^m: expected a number in \[5, 90\), got "):
            half("m", v)
    with pytest.raises(ParamError, match=r"got 90$"):
        half.parse("90")
    with pytest.raises(ParamError, match="^q: expected a probability, got 2$"):
        number(0, hi=1, what="a probability")("q", 2)
