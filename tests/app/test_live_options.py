"""The live commands' options (demo, run, replay, fault set/list, scenario): declared once, their
flags and instances from the declaration, a bad value one line naming the field (or the flag)."""
from __future__ import annotations

from pathlib import Path

import pytest

from sitl.app.args import UsageError, options_of, repeatable
from sitl.app.cli import ScenarioOptions, build_parser, main
from sitl.app.launcher import DemoOptions, ReplayOptions, RunOptions
from sitl.app.live_faults import DEFAULT_OUTS, FaultListOptions, FaultSetOptions
from sitl.params import ParamError, default_of, string


@pytest.mark.parametrize("cls, kw, field", [
    (DemoOptions, {"speed": 0}, "speed"),
    (DemoOptions, {"seed": -1}, "seed"),
    (DemoOptions, {"zenoh": ["tcp/a:1", 3]}, "zenoh"),
    (RunOptions, {"scenario": Path("s.toml"), "duration": -1.0}, "duration"),
    (RunOptions, {"scenario": Path("s.toml"), "quiet": 1}, "quiet"),
    (FaultListOptions, {"timeout": 0}, "timeout"),
    (FaultListOptions, {"timeout": 3600}, "timeout"),
    (FaultSetOptions, {"link": "mav:1", "spec": []}, "spec"),
    (ScenarioOptions, {"out": "/no/such/dir/x.toml"}, "out"),  # a text is read as the flag's word
])
def test_a_bad_value_is_one_line_naming_the_field(cls, kw, field):
    with pytest.raises(ParamError) as exc:
        cls(**kw)
    text = str(exc.value)
    assert text.startswith(f"{field}: ") and "\n" not in text


def test_a_path_option_reads_a_text():
    assert ReplayOptions(log="b.log", json="r.json") == ReplayOptions(log=Path("b.log"), json=Path("r.json"))


def test_parsed_flags_give_the_instance():
    ns = build_parser().parse_args(["run", "s.toml", "--speed", "2", "--zenoh", "tcp/h:1", "--zenoh", "tcp/h:2",
                                    "--no-mavlink"])
    o = options_of(RunOptions, ns)
    assert o == RunOptions(scenario=Path("s.toml"), speed=2.0, zenoh=["tcp/h:1", "tcp/h:2"], no_mavlink=True)
    assert o.out == Path("out/run") and o.seed is None and o.gcs is None
    d = options_of(DemoOptions, build_parser().parse_args(["demo"]))
    assert d == DemoOptions() and d.out == Path("out/demo")
    f = options_of(FaultSetOptions, build_parser().parse_args(["fault", "set", "mav:1", "loss=1%", "delay=5ms"]))
    assert f.spec == ["loss=1%", "delay=5ms"] and f.timeout == 5.0 and isinstance(f.timeout, float)


def test_defaults_are_read_not_written_twice(capsys):
    from sitl.scenario import MavlinkSection

    assert DEFAULT_OUTS == (str(default_of(DemoOptions, "out")), str(default_of(RunOptions, "out")))
    with pytest.raises(SystemExit):
        build_parser().parse_args(["demo", "--help"])
    assert f"(default {default_of(MavlinkSection, 'gcs')})" in capsys.readouterr().out


def test_repeatable():
    check = repeatable(string())
    assert check("k", None) is None
    assert check("k", ("a", "b")) == ["a", "b"]
    with pytest.raises(ParamError, match=r"^k: expected a list"):
        check("k", "a")


def test_options_of_a_bad_namespace_is_a_usage_error():
    import argparse

    with pytest.raises(UsageError, match="timeout: expected seconds in"):
        options_of(FaultListOptions, argparse.Namespace(out=None, zenoh=None, run=None, timeout=-1.0))


@pytest.mark.parametrize("value", ["0", "3600", "nan", "abc"])
def test_fault_timeout_usage_error_exit_2_one_line(value, capsys):
    assert main(["fault", "list", "--zenoh", "tcp/127.0.0.1:1", "--timeout", value]) == 2
    err = capsys.readouterr().err
    assert "--timeout: expected seconds in (0, 3600)" in err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
