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
