"""The experiments' Python API (sitl.app.experiments.run): the typed result holds the same
figures as the command line's result.json for the same arguments, each typed field is its
result.json entry, it plots itself, bad options are one-line usage errors, and README's example
runs as written."""
from __future__ import annotations

import json
import re
import tempfile
from pathlib import Path

import pytest

from sitl.app import experiments
from sitl.app.args import UsageError
from sitl.app.cli import main

README = Path(__file__).resolve().parents[2] / "README.md"
VOLATILE = re.compile(r"wall|timing|bus_cost")  # what differs run to run: durations, costs


def _stable(v):
    """The document without durations, and its provenance without the start and the out dir."""
    if isinstance(v, dict):
        out = {k: _stable(x) for k, x in v.items() if not VOLATILE.search(k)}
        if "started_utc" in out:
            out.pop("started_utc")
            line = out.pop("command_line")
            i = line.index("--out")
            out["command_line"] = line[:i] + line[i + 2:]
        return out
    if isinstance(v, list):
        return [_stable(x) for x in v]
    return v


SMALL = {  # the same small runs as the provenance tests'
    "ekf-vs-ukf": {"trials": 4, "steps": 8, "seed": 2},
    "iono-tropo": {"duration": 20, "trials": 2, "seed": 7},
    "beacon": {"duration": 110, "trials": 1, "sweep_trials": 1, "uav_counts": [3], "seed": 3},
    "sonde": {"duration": 60, "trials": 1, "seed": 4},
    "integrity": {"duration": 100, "trials": 4, "seed": 5},
    "long-run": {"duration": 400, "window": 400, "trials": 1, "no_sonde": True, "seed": 2},
}


def _cli_doc(tmp_path, name, options):
    argv = experiments.command_line(name, tmp_path / "cli", **options)
    assert main(argv) == 0
    return json.loads((tmp_path / "cli" / "result.json").read_text())


def _check_same(r, doc, name):
    assert isinstance(r, experiments.RESULT_TYPES[name]) and r.experiment == name
    assert _stable(r.document) == _stable(doc)  # every figure of result.json, run by the command line
    for key in type(r).HEADLINE:  # the typed fields are result.json's entries
        assert getattr(r, key) == json.loads((r.out / "result.json").read_text()).get(key), key
        assert _stable(getattr(r, key)) == _stable(doc.get(key)), key
    assert (r.seed, r.trials, r.schema) == (doc["seed"], doc["trials"], doc["schema"])
    assert r.provenance.scenario_sha256 == doc["provenance"]["scenario_sha256"]
    assert [f.name for f in r.figures] == doc["figures"] and all(f.is_file() for f in r.figures)


def test_ekf_vs_ukf_through_the_api_is_the_command_lines_result(tmp_path):
    name, options = "ekf-vs-ukf", SMALL["ekf-vs-ukf"]
    r = experiments.run(name, out=tmp_path / "api", **options)
    _check_same(r, _cli_doc(tmp_path, name, options), name)
    assert r.steps == 8 and len(r.pcrb_position_m) == 8
    assert r.provenance.command_line[:3] == ["skyfuse", "experiment", "ekf-vs-ukf"]
    fig = r.plot()
    assert len([a for a in fig.axes if a.images]) == len(r.figures)
    import matplotlib.pyplot as plt
    plt.close(fig)
    assert experiments.ExperimentResult.load(tmp_path / "cli" / "result.json").document["seed"] == 2


@pytest.mark.slow
@pytest.mark.parametrize("name", [n for n in SMALL if n != "ekf-vs-ukf"])
def test_every_experiment_through_the_api_is_the_command_lines_result(tmp_path, name):
    r = experiments.run(name, out=tmp_path / "api", **SMALL[name])
    _check_same(r, _cli_doc(tmp_path, name, SMALL[name]), name)


@pytest.mark.parametrize("name, options, text", [
    ("beacon", {"uavz": 3}, "unknown option uavz="),
    ("beacon", {"trials": -1}, "--trials"),
    ("beacon", {"out": "x"}, None),  # out is run()'s own argument
    ("no-such", {}, "unknown experiment"),
    ("long-run", {"no_sonde": "yes"}, "switch"),
])
def test_bad_options_are_one_line_usage_errors(name, options, text):
    with pytest.raises((UsageError, TypeError)) as e:
        experiments.command_line(name, "o", **options) if text != "--trials" else experiments.run(name, **options)
    if text is not None:
        assert isinstance(e.value, UsageError) and text in str(e.value) and "\n" not in str(e.value)


def _readme_api_example() -> str:
    text = README.read_text(encoding="utf-8")
    section = text[text.index("## Python API"):]
    section = section[:section.index("\n## ", 4)]
    blocks = re.findall(r"```python\n(.*?)```", section, flags=re.S)
    assert len(blocks) == 1, "README's Python API section has one python example"
    return blocks[0]


def test_the_readme_example_runs(tmp_path, monkeypatch, capsys):
    import matplotlib
    matplotlib.use("Agg")
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))  # its default out dir: here, removed after
    code = _readme_api_example()
    env: dict = {}
    exec(compile(code, "README.md (Python API)", "exec"), env)
    r = env["r"]
    printed = capsys.readouterr().out.splitlines()
    assert printed[0] == "BeaconResult 1 2 3"
    assert float(printed[1]) == json.loads((r.out / "result.json").read_text())["cases"]["constellation"]["rmse_m"]
    assert Path(r.out).parent == tmp_path and env["fig"].axes


STUDIES = {  # small studies: (experiment, options, the study's result type, the file the command line writes)
    "sonde-seeds": ("sonde", {"seeds": 2, "seed": 5, "duration": 30}, "SondeSeedStudyResult", "result.json"),
    "iono-tropo-ordering": ("iono-tropo", {"study": "ordering", "seeds": 2, "trials": 1, "duration": 3, "seed": 3},
                            "IonoTropoOrderingStudyResult", "ordering_study.json"),
    "iono-tropo-adaptive-q": ("iono-tropo", {"study": "adaptive-q", "trials": 1, "duration": 3, "seed": 3},
                              "IonoTropoAdaptiveQStudyResult", "adaptive_q_study.json"),
}


@pytest.mark.slow
@pytest.mark.parametrize("study", list(STUDIES))
def test_the_studies_through_the_api_are_the_command_lines_result(tmp_path, study):
    """`--seeds` / `--study` runs through run(): the typed study result holds the same figures as
    the file the command line writes for the same flags, its typed fields are that file's entries,
    and it plots its figure."""
    name, options, type_name, doc_file = STUDIES[study]
    r = experiments.run(name, out=tmp_path / "api", **options)
    assert type(r) is getattr(experiments, type_name) and type(r) in experiments.STUDY_TYPES.values()
    assert r.experiment == name and (r.out / doc_file).is_file()
    argv = experiments.command_line(name, tmp_path / "cli", **options)
    assert main(argv) == 0
    doc = json.loads((tmp_path / "cli" / doc_file).read_text())
    assert doc["study"] == r.document["study"] and _stable(r.document) == _stable(doc)
    assert type(r).HEADLINE and all(_stable(getattr(r, k)) == _stable(doc[k]) for k in type(r).HEADLINE)
    assert r.schema == doc["schema"] and r.provenance.scenario_sha256 == doc["provenance"]["scenario_sha256"]
    assert r.provenance.command_line[:3] == ["skyfuse", "experiment", name]
    assert [f.name for f in r.figures] == doc["figures"] and all(f.is_file() and f.suffix == ".png" for f in r.figures)
    import matplotlib.pyplot as plt
    fig = r.plot()
    assert len([a for a in fig.axes if a.images]) == len(r.figures) >= 1
    plt.close(fig)
    assert type(experiments.ExperimentResult.load(tmp_path / "cli" / doc_file)) is type(r)
