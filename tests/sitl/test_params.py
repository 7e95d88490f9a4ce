"""Parameters declared once (sitl.params): the scenario's validation, its documented default and
`skyfuse scenario` all come from the same declarations."""
import dataclasses
import subprocess
import sys
import tomllib

import pytest

from sitl import scenario as S
from sitl.params import checks, docs, param, toml_table, toml_value

SECTIONS = {"run": S.RunSection, "bus": S.BusSection, "mavlink": S.MavlinkSection, "uavs": S.UavSection,
            "beacon": S.BeaconSection, "sonde": S.SondeSection, "ground_station": S.GroundStationSection}


def test_every_scenario_key_is_declared_with_a_check_and_a_doc():
    for name, cls in SECTIONS.items():
        names = [f.name for f in dataclasses.fields(cls)]
        assert list(checks(cls)) == names, name  # nothing undeclared, in declaration order
        assert all(len(d) > 10 for d in docs(cls).values()), name


def test_the_documented_default_is_the_default_and_names_every_key():
    doc = tomllib.loads(S.DEFAULT_SCENARIO_TOML)
    assert set(doc) == set(SECTIONS)
    for name, cls in SECTIONS.items():
        assert set(doc[name]) == set(checks(cls)), name
    assert S.parse_scenario(S.DEFAULT_SCENARIO_TOML).to_dict() == S.Scenario().to_dict()
    # each key is preceded by its doc
    lines = S.DEFAULT_SCENARIO_TOML.splitlines()
    i = lines.index("lag_window_s = 5.0")
    assert lines[i - 1].startswith("# late (out-of-sequence) measurements")


def test_a_changed_default_changes_everything_that_comes_from_it():
    """One declaration: a section with another default gives that default to the validation's
    result, to the documented TOML and to a parsed empty section alike."""
    @dataclasses.dataclass(frozen=True)
    class Section:
        rate_hz: float = param(2.5, check=lambda k, v: S._number(k, v, lo=0, lo_open=True), doc="epochs per second")

    assert "rate_hz = 2.5" in toml_table("x", Section())
    assert checks(Section)["rate_hz"]("x.rate_hz", 4) == 4.0
    with pytest.raises(S.ScenarioError, match=r"^scenario: x\.rate_hz: expected a finite number > 0, got -1.0$"):
        checks(Section)["rate_hz"]("x.rate_hz", -1)


def test_a_parameter_needs_a_check_and_a_doc():
    with pytest.raises(TypeError):
        param(1, check=None, doc="x")
    with pytest.raises(TypeError):
        param(1, check=lambda k, v: v, doc="")


@pytest.mark.parametrize("v, text", [(True, "true"), (3, "3"), (0.1, "0.1"), ("a\"b", '"a\\"b"'),
                                     ((1.0, (2, 3)), "[1.0, [2, 3]]"), ((), "[]")])
def test_toml_values_read_back_exactly(v, text):
    assert toml_value(v) == text
    back = tomllib.loads(f"k = {text}")["k"]
    norm = (lambda x: tuple(norm(y) for y in x) if isinstance(x, list) else x)
    assert norm(back) == v


def test_skyfuse_scenario_prints_the_documented_default(tmp_path):
    r = subprocess.run([sys.executable, "-c", "import sys; from sitl.app.cli import main; sys.exit(main(['scenario']))"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and r.stdout == S.DEFAULT_SCENARIO_TOML
    out = tmp_path / "s.toml"
    r = subprocess.run([sys.executable, "-c", f"import sys; from sitl.app.cli import main; sys.exit(main(['scenario', '--out', {str(out)!r}]))"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and S.load_scenario(out).to_dict() == S.default_scenario().to_dict()


# ---------------------------------------------------------------- options on the command line
# One declaration gives the flag, its --help text with the default, its argument type (the
# check) and the usage error (exit 2, one line).

from sitl.params import (  # noqa: E402
    ParamError, add_flags, choice, default_of, integer, number, optional, options_from_args, several, switch, validate)


@dataclasses.dataclass(frozen=True)
class _Options:
    trials: int = param(20, check=integer(lo=1), doc="Monte Carlo trials")
    sigma_pr: float = param(6.0, check=number(0, lo_open=True), metavar="M", doc="pseudorange noise sigma, m",
                            note=", as in the seed")
    gain: float | None = param(None, check=optional(number(0)), doc="adaptive gain", shown=lambda: 0.7)
    backend: str = param("auto", check=choice("auto", "numpy"), doc="kernels")
    window_s: list | None = param(None, check=optional(several(number(0), 2)), metavar=("A", "B"), doc="window, s")
    range_step_m: float = param(0.0, check=number(), flag="--range-step", doc="range step, m (100 %)")
    quiet: bool = param(False, check=switch(), doc="no progress lines")

    __post_init__ = validate


def _parser():
    from sitl.app.args import Parser

    p = Parser(prog="t")
    add_flags(p, _Options)
    return p


def test_a_declared_option_gives_its_flag_help_and_default():
    p = _parser()
    help_ = " ".join(p.format_help().split())
    assert "--trials TRIALS Monte Carlo trials (default 20)" in help_
    assert "--sigma-pr M pseudorange noise sigma, m (default 6, as in the seed)" in help_
    assert "--gain GAIN adaptive gain (default 0.7)" in help_  # a None option shows what it stands for
    assert "--backend {auto,numpy} kernels (default auto)" in help_
    assert "--window-s A B window, s" in help_ and "--range-step RANGE_STEP_M range step, m (100 %) (default 0)" in help_
    assert "--quiet no progress lines" in help_
    ns = p.parse_args([])
    assert options_from_args(_Options, ns) == _Options()  # the declared defaults, in one place
    ns = p.parse_args(["--trials", "3", "--range-step", "-2.5", "--window-s", "1", "2", "--quiet"])
    assert ns.range_step_m == -2.5 and ns.window_s == [1.0, 2.0]
    o = options_from_args(_Options, ns)
    assert (o.trials, o.quiet, o.sigma_pr) == (3, True, 6.0)
    assert default_of(_Options, "sigma_pr") == 6.0


@pytest.mark.parametrize("argv, needle", [
    (["--trials", "0"], "argument --trials: expected a positive integer, got 0"),
    (["--trials", "ten"], "argument --trials: expected a positive integer, got 'ten'"),
    (["--sigma-pr", "nan"], "argument --sigma-pr: expected a positive finite number, got nan"),
    (["--sigma-pr", "x"], "argument --sigma-pr: expected a positive number, got 'x'"),
    (["--gain", "-1"], "argument --gain: expected a finite number >= 0, got -1"),
    (["--backend", "gpu"], "invalid choice"),
    (["--window-s", "1"], "expected 2 arguments"),
])
def test_a_bad_value_is_a_usage_error_of_one_line(argv, needle):
    from sitl.app.args import UsageError

    with pytest.raises(UsageError) as exc:
        _parser().parse_args(argv)
    assert needle in str(exc.value) and "\n" not in str(exc.value)


def test_the_same_checks_validate_an_instance():
    with pytest.raises(ParamError, match=r"^trials: expected a positive integer, got 0$"):
        _Options(trials=0)
    with pytest.raises(ParamError, match=r"^backend: expected one of auto, numpy, got 'gpu'$"):
        _Options(backend="gpu")
    assert _Options(sigma_pr=2).sigma_pr == 2.0 and isinstance(_Options(sigma_pr=2).sigma_pr, float)


def test_a_command_line_option_needs_a_check_that_reads_text():
    @dataclasses.dataclass(frozen=True)
    class Bad:
        x: int = param(1, check=lambda k, v: v, doc="a plain check")

    from sitl.app.args import Parser

    with pytest.raises(TypeError, match="sitl.params.Check"):
        add_flags(Parser(prog="t"), Bad)


def test_bad_flags_exit_2_with_one_line_through_skyfuse(capsys):
    from sitl.app.cli import main

    assert main(["experiment", "sonde", "--relay-step-at", "1", "-2"]) == 2
    err = capsys.readouterr().err
    assert "--relay-step-at" in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err


def test_every_experiment_and_bench_declares_its_options():
    """No hand-written flags left: each subcommand's flags are exactly its Options' fields, each
    with a doc, and --help shows every non-None default."""
    import argparse

    from sitl.app import cli

    for table in (cli.EXPERIMENTS, cli.BENCHES):
        for name, (load, _) in table.items():
            mod = load()
            (cls,) = [v for k, v in vars(mod).items() if k.endswith("Options") and dataclasses.is_dataclass(v)
                      and v.__module__ == mod.__name__]
            p = argparse.ArgumentParser()
            mod.add_args(p)
            dests = [a.dest for a in p._actions if a.dest != "help"]
            assert dests == [f.name for f in dataclasses.fields(cls)], name
            assert all(len(d) > 3 for d in docs(cls).values()), name
