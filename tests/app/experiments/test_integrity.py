"""`skyfuse experiment integrity` and `skyfuse bench integrity` (seed 003, issue 6): result.json keys,
figures, usage errors, determinism, the monitor's harmlessness on fault-free data."""
from __future__ import annotations


import numpy as np
import pytest

from tests.outputs import is_png as _is_png
from tests.outputs import strict_json as _strict_json
from sitl.app.cli import main
from sitl.app.experiments import integrity as ex

SHORT = ["experiment", "integrity", "--duration", "100", "--trials", "4", "--seed", "5", "--quiet"]


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("integrity")
    rc = main(SHORT + ["--out", str(out)])
    return rc, out


@pytest.mark.slow
def test_tiny_run_writes_result_keys_and_figures(tiny_run):
    rc, out = tiny_run
    assert rc == 0
    res = _strict_json((out / "result.json").read_text())
    assert res["experiment"] == "integrity" and res["trials"] == 4
    for kind in ("step", "ramp", "outlier"):
        d = res["detection"][kind]
        assert set(d) >= {"pd", "pfa", "mean_delay_s"}
        assert 0.0 <= d["pfa"]["value"] <= 1.0 and len(d["pfa"]["ci95"]) == 2
    assert set(res["position_rmse_m"]) == {"plain", "adaptive_robust", "adaptive_robust_with_bias_estimation"}
    assert all(v > 0 for v in res["position_rmse_m"].values())
    assert set(res["detection_by_filter"]) == {"adaptive_robust", "adaptive_robust_with_bias_estimation"}
    assert res["channels"] >= ex.MIN_CHANNELS
    for f in ex.FIGURES:
        assert _is_png(out / f), f
    assert sorted(res["figures"]) == sorted(ex.FIGURES)


@pytest.mark.slow
def test_same_seed_same_numbers(tiny_run, tmp_path):
    _, first = tiny_run
    out = tmp_path / "again"
    assert main(SHORT + ["--out", str(out)]) == 0

    def drop_wall(d):
        if isinstance(d, dict):
            return {k: drop_wall(v) for k, v in d.items() if k != "wall_s"}
        return d

    a = drop_wall(_strict_json((first / "result.json").read_text()))
    b = drop_wall(_strict_json((out / "result.json").read_text()))
    # the provenance names the run (its --out, its start time); its seed and scenario are the same
    pa, pb = a.pop("provenance"), b.pop("provenance")
    assert (pa["seed"], pa["scenario_sha256"]) == (pb["seed"], pb["scenario_sha256"])
    assert a == b
    out2 = tmp_path / "other"
    assert main(["experiment", "integrity", "--duration", "100", "--trials", "4", "--seed", "6", "--quiet",
                 "--out", str(out2)]) == 0
    c = drop_wall(_strict_json((out2 / "result.json").read_text()))
    assert c["position_rmse_m"] != a["position_rmse_m"]


@pytest.mark.parametrize("extra, needle", [
    (["--trials", "0"], "positive integer"),
    (["--seed", "-1"], "integer >= 0"),
    (["--duration", "-5"], "--duration"),
    (["--duration", "50"], "--duration"),  # no room for the fault onsets after 60 s
    (["--el-mask-deg", "60"], "satellites in view"),
    (["--el-mask-deg", "95"], "--el-mask-deg"),
    (["--jump-sigma", "0"], "--jump-sigma"),
    (["--window-alpha", "2"], "--window-alpha"),
    (["--outlier-prob", "1.5"], "--outlier-prob"),
    (["--backend", "gpu"], "invalid choice"),
    (["--ramp-kind", "slow"], "invalid choice"),
])
def test_usage_errors_exit_2_with_one_line(extra, needle, tmp_path, capsys):
    out = tmp_path / "never"
    assert main(["experiment", "integrity", "--out", str(out), *extra]) == 2
    err = capsys.readouterr().err
    assert needle in err, err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert not (out / "result.json").exists()


@pytest.mark.slow
def test_fault_free_monitor_is_no_worse_than_without():
    """Paired over trials on the same fault-free data: the EKF whose model matches the world, with and
    without the monitor (the same IntegrityConfig as the experiment). "Statistically no worse": the
    one-sided paired test does not find the monitored filter worse (z < 1.645), and the upper 95 %
    bound of the mean per-trial RMSE difference stays within 10 % of the RMSE (20 short trials: one
    early false exclusion moves a trial by ~1 m; the 200-trial, 300 s experiment measures
    +0.0025 +- 0.0058 m on 3.03 m since the adaptive R weights its samples by their precision, +0.069
    +- 0.023 m before).
    Before excluded channels were exempted from the window tests, an early false exclusion
    cascaded in one trial (+9 m there) and this failed."""
    scn = ex.IntegrityScenario(duration_s=150.0, faults=False)
    res = ex.run(scn, 20, seed=11)
    ff = res["fault_free"]["bias_state_model"]
    d = ff["paired_difference_m"]
    base = ff["position_rmse_m"]["without_monitor"]
    assert d["mean"] < 1.645 * d["standard_error"], (d, base)
    assert d["upper_95"] <= 0.10 * base, (d, base)
    a = res["position_rmse_per_trial_m"]["bias_states_fault_free"]
    b = res["position_rmse_per_trial_m"]["bias_states_monitored_fault_free"]
    assert a.shape == b.shape == (20,) and np.all(np.isfinite(a)) and np.all(np.isfinite(b))
    assert np.max(b - a) < 0.75 * base  # no trial cascades
    assert ff["pfa"]["value"] <= 0.003


def test_bench_runs_tiny_and_writes_json(tmp_path, capsys):
    path = tmp_path / "b.json"
    assert main(["bench", "integrity", "--trials", "50", "--steps", "2", "--rounds", "1", "--quiet",
                 "--json", str(path)]) == 0
    res = _strict_json(path.read_text())
    assert res["trials"] == 50 and res["step_s"]["plain"] > 0 and res["step_s"]["monitored"] > 0
    assert "monitor adds" in capsys.readouterr().out


@pytest.mark.parametrize("extra, needle", [(["--trials", "0"], "positive integer"),
                                           (["--rounds", "x"], "positive integer"),
                                           (["--backend", "gpu"], "invalid choice")])
def test_bench_bad_flags_exit_2(extra, needle, capsys):
    assert main(["bench", "integrity", *extra]) == 2
    err = capsys.readouterr().err
    assert needle in err and len(err.strip().splitlines()) == 1


def test_a_clock_ramp_also_shows_in_the_pseudorange_rate():
    """ramp_kind="clock": a satellite clock frequency fault, so the ramp's channel gets the rate as a
    step on its pseudorange-rate column, from the same onset; "code" leaves the rate alone."""
    rng_kw = {"trials": 6, "S": 8}
    for kind in ("code", "clock"):
        scn = ex.IntegrityScenario(duration_s=150.0, ramp_kind=kind)
        faults, truth = ex._faults(scn, np.random.default_rng(5), **rng_kw)
        ramps = [f for f in faults if f.kind == "ramp"]
        rate_steps = [f for f in faults if f.kind == "step" and f.channel >= 8]
        assert len(ramps) == 6
        if kind == "code":
            assert rate_steps == []
        else:
            assert [(f.channel - 8, f.t_start_s, f.magnitude, f.trial) for f in rate_steps] == \
                [(r.channel, r.t_start_s, r.rate, r.trial) for r in ramps]
    with pytest.raises(ValueError, match="ramp_kind"):
        ex.IntegrityScenario(duration_s=150.0, ramp_kind="slow")


@pytest.mark.slow
def test_ramp_signature_snr_equals_the_dense_gls_on_the_whole_history():
    """The oracle's SNR (steady-state Kalman innovations, the Willsky-Jones failure signature) against
    an independent computation: the generalised-least-squares SNR s' C^-1 s of the ramp on the channel's
    whole error history (long before the onset, where the ramp is zero), with C the white plus
    Gauss-Markov covariance written out densely. Short time constants keep the matrix small."""
    import math

    import scipy.linalg

    sw, sg, tau, dt, n, pre = 3.0, 2.0, 20.0, 1.0, 12, 600
    _, snr = ex.ramp_signature(sw, sg, tau, dt, n)
    t = np.arange(pre + n) * dt
    cov = sw**2 * np.eye(t.size) + sg**2 * np.exp(-np.abs(t[:, None] - t[None, :]) / tau)
    for j in (1, 5, n - 1):
        s = np.zeros(t.size)
        s[pre:pre + j + 1] = np.arange(j + 1) * dt  # the ramp up to epoch j after the onset; later data unused
        sub = slice(0, pre + j + 1)
        f = scipy.linalg.cho_factor(cov[sub, sub])
        dense = math.sqrt(s[sub] @ scipy.linalg.cho_solve(f, s[sub]))
        assert snr[j] == pytest.approx(dense, rel=1e-6)
    # no Gauss-Markov error: the matched filter of a ramp in white noise, sqrt(sum (j dt)^2) / sigma
    _, snr0 = ex.ramp_signature(6.0, 0.0, 100.0, 0.1, 101)
    assert snr0[-1] == pytest.approx(math.sqrt(np.sum((np.arange(101) * 0.1) ** 2)) / 6.0, rel=1e-12)


def test_ramp_oracle_pd_single_test_is_the_analytic_two_sided_power():
    """With one epoch after the onset the oracle runs one test: Pd = P(|N(r snr, 1)| > z_(1-pfa/2)),
    analytic; over a 10 s window it is higher, monotone in the rate, and 0.5 m/s ramps in the default
    world (6 m white + 2 m Gauss-Markov) stay far below 0.99 (the issue's ramp target is out of reach)."""
    import scipy.stats

    scn = ex.IntegrityScenario(ramp_detect_s=1.0, dt_s=1.0, duration_s=150.0)
    _, snr = ex.ramp_signature(scn.sigma_pr_m, scn.gm_sigma_m, scn.gm_tau_s, scn.dt_s, 2)
    rates = np.array([2.0, 5.0, 8.0])
    pd = ex.ramp_oracle_pd(rates, scn, 0.003, np.random.default_rng(4), draws=200_000)
    thr = scipy.stats.norm.isf(0.0015)
    mu = rates * snr[1]
    exact = scipy.stats.norm.sf(thr - mu) + scipy.stats.norm.cdf(-thr - mu)
    se = np.sqrt(exact * (1 - exact) / 200_000)
    assert np.all(np.abs(pd - exact) <= 4 * se + 1e-12), (pd, exact)
    full = ex.ramp_oracle_pd([0.5, 0.75, 1.0], ex.IntegrityScenario(), 0.003, np.random.default_rng(4), draws=20_000)
    assert np.all(np.diff(full) > 0) and full[0] < 0.9 and full[2] > 0.99
