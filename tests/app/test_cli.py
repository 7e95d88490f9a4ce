"""The `skyfuse` command line: help, usage errors (exit 2, one line) and a tiny run."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from sitl.app.cli import build_parser, main

SUBCOMMANDS = [[], ["demo"], ["run"], ["replay"], ["bench", "live"], ["experiment"], ["experiment", "ekf-vs-ukf"], ["experiment", "iono-tropo"], ["bench"],
               ["bench", "filters"], ["bench", "iono-tropo"], ["bench", "mavlink"]]


@pytest.mark.parametrize("words", SUBCOMMANDS)
def test_help_on_every_subcommand(words, capsys):
    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args(words + ["--help"])
    assert exc.value.code == 0
    assert "usage:" in capsys.readouterr().out


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["experiment", "ekf-vs-ukf", "--trials", "-5"], "positive integer"),
        (["experiment", "ekf-vs-ukf", "--trials", "ten"], "positive integer"),
        (["experiment", "no-such-experiment"], "invalid choice"),
        (["experiment", "ekf-vs-ukf", "--steps", "0"], "positive integer"),
        (["experiment", "ekf-vs-ukf", "--seed", "-1"], "integer >= 0"),
        (["experiment", "ekf-vs-ukf", "--sigma-a", "nan"], "positive finite"),
        (["bench", "filters", "--trials", "0"], "positive integer"),
        (["bench", "mavlink", "--uavs", "250"], "integer in 1..249"),
        (["bench", "iono-tropo", "--duration", "-1"], "positive finite"),
        (["bench", "iono-tropo", "--el-mask-deg", "80", "--duration", "5"], "satellites in view"),
        (["frobnicate"], "invalid choice"),
        ([], "required"),
    ],
)
def test_usage_errors_exit_2_with_one_line(argv, needle, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert needle in err
    assert len(err.strip().splitlines()) == 1
    assert "Traceback" not in err


def test_unwritable_output_directory(tmp_path, capsys):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        if os.access(ro, os.W_OK):  # root ignores permission bits: use a path under a file
            target = tmp_path / "file"
            target.write_text("x")
            out = str(target / "sub")
        else:
            out = str(ro / "sub")
        assert main(["experiment", "ekf-vs-ukf", "--trials", "2", "--out", out]) == 2
    finally:
        ro.chmod(0o700)
    err = capsys.readouterr().err
    assert "output directory" in err and len(err.strip().splitlines()) == 1


@pytest.mark.live
def test_console_script_exit_code_without_traceback():
    # the installed entry point, as a user runs it
    proc = subprocess.run([sys.executable, "-m", "sitl.app.cli", "experiment", "ekf-vs-ukf", "--trials", "-1"],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr and proc.stderr.count("\n") == 1


@pytest.mark.slow
def test_small_experiment_writes_result_and_figures(tmp_path, capsys):
    out = tmp_path / "run"
    rc = main(["experiment", "ekf-vs-ukf", "--trials", "40", "--steps", "30", "--seed", "3",
               "--out", str(out), "--quiet"])
    assert rc == 0
    res = json.loads((out / "result.json").read_text())
    for key in ("trials", "steps", "measurements_per_step", "state_dim", "wall_s", "pcrb_position_m"):
        assert key in res
    assert (res["trials"], res["steps"], res["measurements_per_step"], res["state_dim"]) == (40, 30, 8, 11)
    assert len(res["pcrb_position_m"]) == 30
    for f in ("ekf", "ukf"):
        for key in ("spherical_error_mean_m", "spherical_error_std_m", "rmse_position_m"):
            assert len(res[f][key]) == 30
        assert res[f]["anees"] > 0
    assert (out / "spherical_error.png").stat().st_size > 10_000
    assert (out / "nees.png").stat().st_size > 5_000
    table = capsys.readouterr().out
    assert "sqrt PCRB" in table and "ANEES" in table


def test_experiment_is_deterministic_for_a_seed(tmp_path):
    from sitl.app.experiments.ekf_vs_ukf import EkfVsUkfScenario, run

    a = run(EkfVsUkfScenario(steps=10), 20, seed=5)
    b = run(EkfVsUkfScenario(steps=10), 20, seed=5)
    c = run(EkfVsUkfScenario(steps=10), 20, seed=6)
    assert a["ekf"]["rmse_position_m"] == b["ekf"]["rmse_position_m"]
    assert a["ekf"]["rmse_position_m"] != c["ekf"]["rmse_position_m"]


def test_bad_scenario_values_are_clear():
    from sitl.app.experiments.ekf_vs_ukf import EkfVsUkfScenario

    with pytest.raises(ValueError, match="n_sats must be >= 4"):
        EkfVsUkfScenario(n_sats=3)
    with pytest.raises(ValueError, match="sigma_pr_m"):
        EkfVsUkfScenario(sigma_pr_m=-1.0)
    with pytest.raises(ValueError, match="noise reading"):
        EkfVsUkfScenario.with_noise_reading("cubits")


def test_bench_iono_tropo_runs_and_reports_ratios(tmp_path, capsys):
    out = tmp_path / "b.json"
    assert main(["bench", "iono-tropo", "--duration", "3", "--rounds", "1", "--quiet", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "x real time" in text and "world only" in text
    doc = json.loads(out.read_text())
    assert doc["n_visible_min"] == doc["n_visible_max"] == 12  # the 12 satellites
    cases = {r["case"]: r for r in doc["rows"]}
    main_row = cases["variant 3, numba kernels"]
    assert main_row["ratio_to_main"] == 1.0
    for r in doc["rows"]:
        assert r["wall_s"] > 0 and abs(r["x_real_time"] - 3.0 / r["wall_s"]) < 1e-9 * r["x_real_time"]


def test_a_reader_that_goes_away_ends_the_command_quietly(monkeypatch, capsys, tmp_path):
    """`skyfuse gnss orbits ... | head`: the pipe closes under the writer; no traceback, the
    shell's status for a writer cut off by its reader (128 + SIGPIPE)."""
    import io
    from pathlib import Path

    from sitl.app import cli

    class ClosedPipe(io.TextIOBase):
        def write(self, s):
            raise BrokenPipeError(32, "Broken pipe")

        def fileno(self):
            raise io.UnsupportedOperation("no descriptor")

    data = Path(__file__).resolve().parents[1] / "data" / "gnss"
    monkeypatch.setattr("sys.stdout", ClosedPipe())
    rc = cli.main(["gnss", "orbits", "--nav", str(data / "brdc1820.10n"), "--sp3", str(data / "igs15904.sp3"),
                   "--out", str(tmp_path / "o")])
    assert rc == 141
    assert "Traceback" not in capsys.readouterr().err
