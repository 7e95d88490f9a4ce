"""Provenance everywhere (sitl/app/provenance.py): the record's fields are right (the commit is
git's own `rev-parse HEAD`, the hash follows the scenario, no checkout / no git gives nulls), and
every writer of an output document -- each experiment, the gnss commands, the launcher's
report.json, the benches' --json -- puts it there under the one schema version (each run small)."""
from __future__ import annotations

import datetime as dt
import hashlib
import json
import shutil
import subprocess
import time
from pathlib import Path

import pytest

import sitl
from sitl.app import provenance as pv
from sitl.app.cli import main

FIELDS = {"skyfuse_version", "git_commit", "git_dirty", "command_line", "seed", "scenario_sha256", "scenario",
          "started_utc", "python_version", "numpy_version", "numba_version"}
ROOT = Path(sitl.__file__).resolve().parent.parent
DATA = Path(__file__).resolve().parents[1] / "data" / "gnss"


def _git(*args):
    if shutil.which("git") is None:
        return None
    p = subprocess.run(["git", "-C", str(ROOT), *args], capture_output=True, text=True, timeout=10)
    return p.stdout.strip() if p.returncode == 0 else None


IN_CHECKOUT = _git("rev-parse", "--show-toplevel") is not None and \
    Path(_git("rev-parse", "--show-toplevel")).resolve() == ROOT


# ------------------------------------------------------------------ the record itself
def test_the_record_has_every_field_and_the_versions_of_the_installed_packages():
    from importlib.metadata import version

    import numpy

    p = pv.provenance(["skyfuse", "x"], seed=3, scenario={"a": 1})
    assert set(p) == FIELDS
    assert p["skyfuse_version"] == version("skyfuse")
    assert p["numpy_version"] == numpy.__version__
    assert p["numba_version"] == version("numba")
    assert p["command_line"] == ["skyfuse", "x"] and p["seed"] == 3
    json.dumps(p, allow_nan=False)  # strict JSON as it is


@pytest.mark.skipif(not IN_CHECKOUT, reason="the package is not run from a git checkout")
def test_the_commit_is_gits_head_and_dirty_is_gits_status():
    p = pv.provenance([])
    assert p["git_commit"] == _git("rev-parse", "HEAD")
    assert p["git_dirty"] == bool(_git("status", "--porcelain", "--untracked-files=no"))


def test_no_checkout_or_no_git_gives_nulls_not_an_error(tmp_path, monkeypatch):
    assert pv.git_state(tmp_path) == {"commit": None, "dirty": None}  # not a work tree
    monkeypatch.setenv("PATH", str(tmp_path))  # no git on PATH
    assert pv.git_state() == {"commit": None, "dirty": None}
    assert pv.provenance([])["git_commit"] is None


def test_the_start_time_is_utc_iso8601_and_now():
    pv.mark_started(["skyfuse", "demo"])
    t = dt.datetime.fromisoformat(pv.provenance()["started_utc"])
    assert t.utcoffset() == dt.timedelta(0)
    assert abs(t.timestamp() - time.time()) < 5.0
    assert pv.provenance()["command_line"] == ["skyfuse", "demo"]


def test_the_scenario_hash_follows_the_scenario_not_its_spelling():
    import dataclasses

    import numpy as np

    @dataclasses.dataclass
    class Scn:
        duration_s: float = 10.0
        sats: tuple = (1, 2)

    h = pv.scenario_record({"b": {"x": 1.0, "y": [1, 2]}, "a": 2})["sha256"]
    assert h == pv.scenario_record({"a": 2, "b": {"y": (1, 2), "x": np.float64(1.0)}})["sha256"]  # key order, types
    assert h != pv.scenario_record({"a": 2, "b": {"x": 1.5, "y": [1, 2]}})["sha256"]
    assert h == hashlib.sha256(b'{"a":2,"b":{"x":1.0,"y":[1,2]}}').hexdigest()  # the canonical JSON, by hand
    assert pv.scenario_record(Scn())["dict"] == {"duration_s": 10.0, "sats": [1, 2]}
    assert pv.scenario_record(Scn())["sha256"] != pv.scenario_record(Scn(duration_s=11.0))["sha256"]
    assert pv.scenario_record(None) == {"sha256": None, "dict": None}


def test_the_live_scenarios_hash_changes_with_a_key():
    from sitl.scenario import default_scenario

    scn = default_scenario()
    d = scn.to_dict()
    d["run"]["seed"] = d["run"]["seed"] + 1
    assert pv.scenario_record(scn)["sha256"] == pv.scenario_record(scn.to_dict())["sha256"]
    assert pv.scenario_record(scn)["sha256"] != pv.scenario_record(d)["sha256"]


# ------------------------------------------------------------------ every writer
def _check(path: Path, argv, seed="any"):
    doc = json.loads(path.read_text(), parse_constant=lambda c: pytest.fail(f"non-strict JSON {c} in {path}"))
    assert doc["schema"] == pv.SCHEMA, path
    p = doc["provenance"]
    assert set(p) == FIELDS, path
    assert p["command_line"] == ["skyfuse", *argv]
    if seed != "any":
        assert p["seed"] == seed
    if p["scenario"] is not None:
        text = json.dumps(p["scenario"], sort_keys=True, separators=(",", ":"))
        assert p["scenario_sha256"] == hashlib.sha256(text.encode()).hexdigest()
    if IN_CHECKOUT:
        assert p["git_commit"] == _git("rev-parse", "HEAD")
    assert abs(dt.datetime.fromisoformat(p["started_utc"]).timestamp() - time.time()) < 3600
    return doc


def _run(argv, capsys=None):
    assert main(argv) == 0, argv
    return argv


EXPERIMENTS = {  # small runs of every experiment: (argv after --out DIR, the seed recorded, files)
    "ekf-vs-ukf": (["--trials", "2", "--steps", "5", "--seed", "2"], 2, ["result.json"]),
    "iono-tropo": (["--duration", "20", "--trials", "2", "--seed", "7"], 7, ["result.json"]),
    "integrity": (["--duration", "100", "--trials", "4", "--seed", "5"], 5, ["result.json"]),
    "beacon": (["--duration", "110", "--trials", "1", "--sweep-trials", "1", "--uav-counts", "3", "--seed", "3"], 3,
               ["result.json"]),
    "sonde": (["--duration", "60", "--trials", "1", "--seed", "4"], 4, ["result.json"]),
    "long-run": (["--duration", "400", "--window", "400", "--trials", "1", "--no-sonde", "--seed", "2"], 2,
                 ["result.json"]),
}


@pytest.mark.slow
@pytest.mark.parametrize("name", list(EXPERIMENTS))
def test_every_experiments_result_json_carries_it(tmp_path, name):
    extra, seed, files = EXPERIMENTS[name]
    argv = _run(["experiment", name, "--out", str(tmp_path), "--quiet", *extra])
    for f in files:
        doc = _check(tmp_path / f, argv, seed)
        assert doc["experiment"] == name


@pytest.mark.slow
def test_the_scenario_hash_in_result_json_changes_when_the_scenario_does(tmp_path):
    base = ["experiment", "ekf-vs-ukf", "--trials", "2", "--steps", "5", "--quiet"]
    h = [_check(tmp_path / d / "result.json", _run([*base, "--out", str(tmp_path / d), *x]))["provenance"]
         for d, x in (("a", []), ("b", []), ("c", ["--sigma-a", "0.5"]))]
    assert h[0]["scenario_sha256"] == h[1]["scenario_sha256"] != h[2]["scenario_sha256"]


@pytest.mark.slow
def test_the_study_documents_carry_it(tmp_path):
    argv = _run(["experiment", "sonde", "--seeds", "2", "--seed", "5", "--duration", "60", "--out",
                 str(tmp_path / "s"), "--quiet"])
    _check(tmp_path / "s" / "result.json", argv, [5, 6])
    argv = _run(["experiment", "iono-tropo", "--study", "ordering", "--seeds", "2", "--trials", "2", "--duration", "5",
                 "--out", str(tmp_path / "i"), "--quiet"])
    _check(tmp_path / "i" / "ordering_study.json", argv, [0, 1])


@pytest.mark.slow
def test_the_faults_experiment_carries_it(tmp_path, monkeypatch):
    from sitl.app.experiments import network_faults as fx

    monkeypatch.setattr(fx, "QUICK_PLAN", fx.Plan(loss=(0.5,), burst_loss=(), delay_s=(), partition_s=()))
    monkeypatch.setattr(fx, "QUICK_SETUPS", {"beacon": fx.Setup("beacon", 80.0, 20.0, 40.0, margin_s=20.0),
                                             "sonde": fx.Setup("sonde", 90.0, 30.0, 50.0, margin_s=20.0)})
    argv = _run(["experiment", "faults", "--out", str(tmp_path), "--quick", "--trials", "1", "--quiet", "--seed", "4"])
    _check(tmp_path / "result.json", argv, 4)


def test_the_gnss_orbits_result_carries_it(tmp_path):
    argv = _run(["gnss", "orbits", "--nav", str(DATA / "brdc1820.10n"), "--sp3", str(DATA / "igs15904.sp3"),
                 "--out", str(tmp_path)])
    _check(tmp_path / "result.json", argv, None)


@pytest.mark.slow
def test_the_gnss_solve_and_export_outputs_carry_it(tmp_path):
    argv = _run(["gnss", "solve", str(DATA / "07590920.05o"), "--nav", str(DATA / "07590920.05n"), "--variant",
                 "code_doppler", "--static", "--no-rtklib", "--quiet", "--out", str(tmp_path / "s")])
    _check(tmp_path / "s" / "result.json", argv, None)
    argv = ["gnss", "export", "--receiver", "static", "--duration", "60", "--out", str(tmp_path / "e")]
    if shutil.which("rnx2rtkp"):
        argv.append("--rtklib")
    _run(argv)
    doc = _check(tmp_path / "e" / "export.json", argv)
    assert doc["provenance"]["seed"] == doc["seed"] and doc["provenance"]["scenario"]["run"]["seed"] == doc["seed"]
    if shutil.which("rnx2rtkp"):
        _check(tmp_path / "e" / "rtklib.json", argv, None)


def test_the_batch_runs_report_json_carries_it(tmp_path):
    argv = _run(["demo", "--batch", "--duration", "5", "--seed", "9", "--out", str(tmp_path), "--quiet"])
    doc = _check(tmp_path / "report.json", argv, 9)
    assert doc["provenance"]["scenario"]["run"]["seed"] == 9 and doc["provenance"]["scenario"] == doc["scenario"]


def test_a_bench_json_carries_it(tmp_path):
    out = tmp_path / "b.json"
    argv = _run(["bench", "iono-tropo", "--duration", "3", "--rounds", "1", "--quiet", "--json", str(out)])
    _check(out, argv)
