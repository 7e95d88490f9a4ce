"""`skyfuse experiment iono-tropo` (seed 000): help, usage errors, result.json, figures, determinism."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from tests.outputs import is_png as _is_png
from tests.outputs import strict_json as _strict_json
from sitl.app.cli import build_parser, main
from sitl.app.provenance import SCHEMA

VARIANTS = ("code_doppler", "phase_increments", "carrier_phase")
FIGURES = ("iono_tropo_estimates.png", "iono_tropo_errors.png", "iono_tropo_time_to_1m.png")
VARIANT_KEYS = ("time_to_1m_s", "time_to_1m_s_per_trial", "final_error_m", "final_bias_m", "anees",
                "anees_bounds_99_one_epoch", "wall_s")
SHORT = ["experiment", "iono-tropo", "--duration", "20", "--trials", "2", "--seed", "7", "--quiet"]


@pytest.fixture(scope="module")
def all_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("it_all")
    rc = main(SHORT + ["--variant", "all", "--out", str(out)])
    return rc, out


def test_help_lists_the_variants(capsys):
    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args(["experiment", "iono-tropo", "--help"])
    assert exc.value.code == 0
    text = capsys.readouterr().out
    assert "usage:" in text
    for name in VARIANTS + ("all",):
        assert name in text
    with pytest.raises(SystemExit):
        build_parser().parse_args(["experiment", "--help"])
    assert "iono-tropo" in capsys.readouterr().out


@pytest.mark.slow
def test_all_variants_write_result_series_and_figures(all_run, capsys):
    rc, out = all_run
    assert rc == 0
    res = _strict_json((out / "result.json").read_text())
    assert res["experiment"] == "iono-tropo" and res["schema"] == SCHEMA
    assert (res["seed"], res["trials"]) == (7, 2)
    assert res["scenario"]["duration_s"] == 20.0 and res["scenario"]["sigma_pr_m"] == 6.0
    assert set(res["variants"]) == set(VARIANTS)
    for name in VARIANTS:
        v = res["variants"][name]
        for key in VARIANT_KEYS:
            assert key in v, (name, key)
        assert set(v["final_error_m"]) == {"iono_zenith", "tropo_zenith", "position"}
        assert len(v["time_to_1m_s_per_trial"]) == 2
        assert len(v["anees_bounds_99_one_epoch"]) == 2
    assert "increments" in res["variants"]["phase_increments"]
    assert "ambiguity" in res["variants"]["carrier_phase"]
    assert "increments" not in res["variants"]["code_doppler"]
    assert res["paper"]["code_doppler"]["time_to_1m_s"] == 500
    assert res["paper"]["phase_increments"]["time_to_1m_s"] == 350
    assert res["paper"]["carrier_phase"]["time_to_1m_s"] == "practically at once"
    assert res["ordering_3_lt_2_lt_1"] in (True, False)
    assert sorted(res["figures"]) == sorted(FIGURES)
    for f in FIGURES:
        assert _is_png(out / f), f
    with np.load(out / "series.npz") as npz:
        for name in VARIANTS:
            assert npz[f"{name}/iono_err_rms_m"].shape == (201,)
            assert npz[f"{name}/t_s"][-1] == pytest.approx(20.0)


@pytest.mark.slow
def test_single_variant_writes_only_that_variant(tmp_path, capsys):
    out = tmp_path / "one"
    assert main(SHORT + ["--variant", "carrier_phase", "--out", str(out)]) == 0
    res = _strict_json((out / "result.json").read_text())
    assert list(res["variants"]) == ["carrier_phase"]
    assert res["ordering_3_lt_2_lt_1"] is None
    for f in FIGURES:
        assert _is_png(out / f), f
    with np.load(out / "series.npz") as npz:
        assert all(k.startswith("carrier_phase/") for k in npz.files)
    table = capsys.readouterr().out
    assert "carrier_phase" in table and "practically at once" in table and "code_doppler" not in table


@pytest.mark.slow
def test_never_settled_is_null_not_infinity(tmp_path):
    # 1 s of code + Doppler cannot bring I_g from 0 to within 1 m of 15 m: time to 1 m is inf
    out = tmp_path / "inf"
    assert main(["experiment", "iono-tropo", "--duration", "1", "--trials", "2", "--quiet",
                 "--variant", "code_doppler", "--out", str(out)]) == 0
    res = _strict_json((out / "result.json").read_text())
    v = res["variants"]["code_doppler"]
    assert v["time_to_1m_s"] is None and None in v["time_to_1m_s_per_trial"]


@pytest.mark.parametrize(
    "extra, needle",
    [
        (["--variant", "nonsense"], "invalid choice"),
        (["--sigma-pr", "-1"], "--sigma-pr"),
        (["--sigma-prr", "0"], "--sigma-prr"),
        (["--sigma-phase", "nan"], "--sigma-phase"),
        (["--el-mask-deg", "80"], "satellites in view"),
        (["--el-mask-deg", "95"], "--el-mask-deg"),
        (["--duration", "-5"], "--duration"),
        (["--duration", "abc"], "--duration"),
        (["--trials", "0"], "positive integer"),
        (["--seed", "-1"], "integer >= 0"),
        (["--adaptive-q", "maybe"], "invalid choice"),
        (["--slip-rate", "-1"], "--slip-rate"),
        (["--adaptive-q-decay", "1"], "--adaptive-q-decay"),
        (["--adaptive-q-gain", "-0.5"], "--adaptive-q-gain"),
        (["--truth-clock-psd-scale", "0"], "--truth-clock-psd-scale"),
        (["--cmc-noise", "independent"], "invalid choice"),
        (["--phase-sats", "-1"], "integer >= 0"),
    ],
)
def test_usage_errors_exit_2_with_one_line(extra, needle, tmp_path, capsys):
    out = tmp_path / "never"
    assert main(["experiment", "iono-tropo", "--out", str(out), *extra]) == 2
    err = capsys.readouterr().err
    assert needle in err
    assert len(err.strip().splitlines()) == 1
    assert "Traceback" not in err
    assert not (out / "result.json").exists()  # the error came before any run


@pytest.mark.slow
@pytest.mark.live
def test_too_few_satellites_through_a_real_process(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "sitl.app.cli", "experiment", "iono-tropo", "--el-mask-deg", "80",
                           "--out", str(tmp_path / "x")], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr and proc.stderr.count("\n") == 1
    assert "only 0 satellites in view" in proc.stderr and "--el-mask-deg" in proc.stderr
    assert proc.stdout == ""


def _without_wall(d):
    if isinstance(d, dict):
        return {k: _without_wall(v) for k, v in d.items() if k != "wall_s"}
    if isinstance(d, list):
        return [_without_wall(v) for v in d]
    return d


@pytest.mark.slow
def test_same_seed_same_numbers(all_run, tmp_path):
    _, first = all_run
    out = tmp_path / "again"
    assert main(SHORT + ["--variant", "all", "--out", str(out)]) == 0
    a = _without_wall(_strict_json((first / "result.json").read_text()))
    b = _without_wall(_strict_json((out / "result.json").read_text()))
    # the provenance names the run (its --out, its start time); its seed and scenario are the same
    pa, pb = a.pop("provenance"), b.pop("provenance")
    assert (pa["seed"], pa["scenario_sha256"]) == (pb["seed"], pb["scenario_sha256"])
    assert a == b
    with np.load(first / "series.npz") as na, np.load(out / "series.npz") as nb:
        assert na.files == nb.files
        for k in na.files:
            np.testing.assert_array_equal(na[k], nb[k])
