"""sitl.netfault.spec: the netem-like fault text -- values in SI units, netem spellings,
one-line errors naming the bad token, and the round trip parse_spec(to_text(s)) == s for
every valid spec (hypothesis)."""
from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sitl.netfault import FaultSpec, FaultSpecError, parse_spec
from sitl.netfault.spec import DISTRIBUTIONS


@pytest.mark.parametrize("text,expected", [
    ("loss=10% delay=100ms~20ms", FaultSpec(loss=0.1, delay_s=0.1, jitter_s=0.02)),
    ("loss=0.1", FaultSpec(loss=0.1)),
    ("loss=10%,25%", FaultSpec(loss=0.1, loss_corr=0.25)),
    ("gemodel=1%,10%,70%,0.1%", FaultSpec(ge=(0.01, 0.1, 0.7, 0.001))),
    ("gemodel=5%", FaultSpec(ge=(0.05, 0.95, 1.0, 0.0))),  # tc-netem(8) defaults: Bernoulli
    ("gemodel=5%,30%", FaultSpec(ge=(0.05, 0.3, 1.0, 0.0))),
    ("delay=2s", FaultSpec(delay_s=2.0)),
    ("delay=0.1s~250us,30%", FaultSpec(delay_s=0.1, jitter_s=250e-6, delay_corr=0.3)),
    ("delay=100ms~20ms distribution=pareto", FaultSpec(delay_s=0.1, jitter_s=0.02, distribution="pareto")),
    ("delay=10ms reorder=25%,50% gap=5",
     FaultSpec(delay_s=0.01, reorder=0.25, reorder_corr=0.5, gap=5)),
    ("delay=10ms reorder=25%", FaultSpec(delay_s=0.01, reorder=0.25, gap=1)),
    ("delay=10ms gap=5", FaultSpec(delay_s=0.01, reorder=1.0, gap=5)),  # kernel: gap -> 100 %
    ("duplicate=1% corrupt=0.1%,5%", FaultSpec(duplicate=0.01, corrupt=0.001, corrupt_corr=0.05)),
    ("rate=1mbit limit=100", FaultSpec(rate_bps=1e6, limit=100)),
    ("rate=64kbit", FaultSpec(rate_bps=64e3)),
    ("rate=9600", FaultSpec(rate_bps=9600.0)),
    ("rate=1kbps", FaultSpec(rate_bps=8000.0)),  # tc: bps = bytes per second
    ("partition=10-20,30.5-40", FaultSpec(partitions=((10.0, 20.0), (30.5, 40.0)))),
    ("none", FaultSpec()),
    ("", FaultSpec()),
    ("   ", FaultSpec()),
    # netem spellings
    ("loss 10%", FaultSpec(loss=0.1)),
    ("loss random 10% 25%", FaultSpec(loss=0.1, loss_corr=0.25)),
    ("loss gemodel 1% 10% 70% 0.1%", FaultSpec(ge=(0.01, 0.1, 0.7, 0.001))),
    ("delay 100ms 20ms 25% distribution normal",
     FaultSpec(delay_s=0.1, jitter_s=0.02, delay_corr=0.25, distribution="normal")),
    ("delay 10ms reorder 25% 50% gap 5 limit 1000",
     FaultSpec(delay_s=0.01, reorder=0.25, reorder_corr=0.5, gap=5, limit=1000)),
    ("LOSS=10%", FaultSpec(loss=0.1)),
])
def test_parse_examples(text, expected):
    s = parse_spec(text)
    assert s == expected
    assert parse_spec(s.to_text()) == s


def test_identity_and_passthrough():
    assert FaultSpec().is_identity and FaultSpec().to_text() == "none"
    assert not parse_spec("loss=1%").is_identity
    s = parse_spec("delay=1s")
    assert parse_spec(s) is s and parse_spec(None) == FaultSpec()
    assert str(s) == "delay=1s"
    assert parse_spec("partition=5-6").down(5.0) and not parse_spec("partition=5-6").down(6.0)


@pytest.mark.parametrize("text,token,what", [
    ("loss=120%", "loss=120%", "expected a percentage in [0, 100]"),
    ("loss=1.5", "loss=1.5", "fraction in [0, 1]"),
    ("loss=-1%", "loss=-1%", "percentage in [0, 100]"),
    ("loss=abc", "loss=abc", "expected a percentage"),
    ("loss=10%,20%,30%", "loss=10%,20%,30%", "expected 1 to 2 values"),
    ("loss=", "loss=", "missing value"),
    ("loss=10% loss=5%", "loss=5%", "given twice"),
    ("loss=10% gemodel=1%", "gemodel=1%", "only one loss model"),
    ("delay=5xs", "delay=5xs", "unknown time unit"),
    ("delay=-5ms", "delay=-5ms", "duration >= 0"),
    ("delay=1s~nan", "delay=1s~nan", "expected a duration"),
    ("delay=1s~inf", "delay=1s~inf", "expected a duration"),
    ("distribution=cauchy delay=1s~1ms", "distribution=cauchy", "expected one of"),
    ("distribution=normal delay=1s", "distribution=normal", "needs a delay jitter"),
    ("reorder=10%", "reorder=10%", "needs a delay"),
    ("gap=0 delay=1s", "gap=0", "integer >= 1"),
    ("gap=2.5 delay=1s", "gap=2.5", "integer"),
    ("rate=fast", "rate=fast", "expected a rate"),
    ("rate=10furlong", "rate=10furlong", "unknown rate unit"),
    ("rate=0mbit", "rate=0mbit", "rate > 0"),
    ("limit=-1", "limit=-1", "integer >= 0"),
    ("partition=20-10", "partition=20-10", "T1 < T2"),
    ("partition=10", "partition=10", "T1-T2"),
    ("foo=1", "foo=1", "unknown key"),
    ("loss=1% bogus", "bogus", "unknown key"),
    ("loss state 1%", "loss state 1%", "not supported"),
    ("gemodel=1%,2%,3%,4%,5%", "gemodel=1%,2%,3%,4%,5%", "expected 1 to 4 values"),
])
def test_bad_specs_one_line_error_naming_the_token(text, token, what):
    with pytest.raises(FaultSpecError) as ei:
        parse_spec(text)
    msg = str(ei.value)
    assert "\n" not in msg
    assert msg.startswith("fault spec: ")
    assert token in msg and what in msg, msg
    assert isinstance(ei.value, ValueError)


def test_bad_types_and_lines():
    for bad in (3, b"loss=1%", ["loss=1%"]):
        with pytest.raises(FaultSpecError):
            parse_spec(bad)
    with pytest.raises(FaultSpecError, match="one line"):
        parse_spec("loss=1%\ndelay=1s")


def test_dataclass_validates():
    for kw in ({"loss": 1.5}, {"loss": -0.1}, {"delay_s": -1.0}, {"delay_s": math.inf},
               {"rate_bps": math.nan}, {"gap": -1}, {"limit": 1.5}, {"distribution": "x"},
               {"ge": (0.1, 0.2)}, {"ge": (0.1, 0.2, 0.3, 1.2)}, {"partitions": ((2.0, 1.0),)},
               {"loss": 0.1, "ge": (0.1, 0.2, 1.0, 0.0)}, {"reorder": 0.5},
               {"distribution": "normal", "delay_s": 1.0}, {"loss": True}):
        with pytest.raises(FaultSpecError):
            FaultSpec(**kw)
    s = FaultSpec(delay_s=1, reorder=0.5)
    assert s.gap == 1 and isinstance(s.delay_s, float)
    with pytest.raises(AttributeError):
        s.loss = 0.5  # frozen


# ---------------------------------------------------------------------------------------
# round trip for every valid spec

fraction = st.one_of(st.just(0.0), st.just(1.0), st.floats(0.0, 1.0),
                     st.integers(0, 1000).map(lambda k: k / 1000))
positive_s = st.one_of(st.floats(1e-9, 1e4), st.integers(1, 5000).map(lambda k: k / 1000))
times = st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False)


@st.composite
def specs(draw) -> FaultSpec:
    kw: dict = {}
    if draw(st.booleans()):
        if draw(st.booleans()):
            kw["ge"] = tuple(draw(fraction) for _ in range(4))
        else:
            kw["loss"] = draw(fraction)
            kw["loss_corr"] = draw(fraction)
    if draw(st.booleans()):
        kw["delay_s"] = draw(st.one_of(st.just(0.0), positive_s))
        if draw(st.booleans()):
            kw["jitter_s"] = draw(positive_s)
            kw["distribution"] = draw(st.sampled_from(DISTRIBUTIONS))
        kw["delay_corr"] = draw(fraction)
    if (kw.get("delay_s") or kw.get("jitter_s")) and draw(st.booleans()):
        kw["reorder"] = draw(fraction)
        kw["reorder_corr"] = draw(fraction)
        kw["gap"] = draw(st.integers(0, 50))
    for name in ("duplicate", "corrupt"):
        if draw(st.booleans()):
            kw[name] = draw(fraction)
            kw[f"{name}_corr"] = draw(fraction)
    if draw(st.booleans()):
        kw["rate_bps"] = draw(st.one_of(st.floats(1.0, 1e11), st.integers(1, 10**9).map(float)))
    if draw(st.booleans()):
        kw["limit"] = draw(st.integers(0, 10**6))
    if draw(st.booleans()):
        n = draw(st.integers(1, 4))
        parts = []
        for _ in range(n):
            a, b = sorted((draw(times), draw(times)))
            parts.append((a, b if b > a else a + 1.0))
        kw["partitions"] = tuple(parts)
    return FaultSpec(**kw)


@settings(max_examples=200, deadline=None)
@given(specs())
def test_round_trip_every_valid_spec(s):
    text = s.to_text()
    assert "\n" not in text
    assert parse_spec(text) == s, text
    assert parse_spec(text).to_text() == text


@settings(max_examples=200, deadline=None)
@given(st.text(alphabet="lossdelay=%,~0123456789.msu-gapratekbitnone \t", max_size=40))
def test_arbitrary_text_parses_or_fails_one_line(text):
    try:
        s = parse_spec(text)
    except FaultSpecError as e:
        assert "\n" not in str(e) and str(e).startswith("fault spec: ")
    else:
        assert parse_spec(s.to_text()) == s
