"""Seed 000 variant 2 (plus code-minus-carrier increments over 90 s, eqs 29-33) against
variant 1 on the same simulated data."""
import numpy as np
import pytest
import scipy.stats

from sitl.experiments import seed000
from sitl.experiments.seed000 import (
    IonoTropoScenario,
    run_cmc_increments,
    run_code_doppler,
    run_streamed,
)

TRIALS = 8
DURATION = 400.0
SLIP_RATE = 0.002  # per tracked satellite, 1/s: ~0.8 slips per satellite in 400 s


@pytest.fixture(scope="module")
def runs():
    scn = IonoTropoScenario(duration_s=DURATION)
    return run_code_doppler(scn, TRIALS, seed=0), run_cmc_increments(scn, TRIALS, seed=0)


@pytest.fixture(scope="module")
def slip_run():
    return run_cmc_increments(IonoTropoScenario(duration_s=DURATION, cycle_slip_rate_hz=SLIP_RATE), TRIALS, seed=0)


def _nees_band():
    # two-sided 99.9 % band of the mean over 8 trials of a chi2(2) NEES (see variant-1 test)
    return (scipy.stats.chi2.ppf(0.0005, 2 * TRIALS) / TRIALS, scipy.stats.chi2.ppf(0.9995, 2 * TRIALS) / TRIALS)


def test_same_simulated_data(runs):
    v1, v2 = runs
    assert v1["variant"] == 1 and v2["variant"] == 2
    np.testing.assert_array_equal(v1["n_visible"], v2["n_visible"])
    assert v1["prior_error"] == v2["prior_error"]
    # identical until the first increment can be formed (after one window)
    t = np.asarray(v1["t_s"])
    early = t < 90.0
    np.testing.assert_array_equal(np.asarray(v1["iono_err_rms_m"])[early], np.asarray(v2["iono_err_rms_m"])[early])


def test_increments_help_on_the_same_data(runs):
    v1, v2 = runs
    inc = v2["increments"]
    assert inc["used"] > 0 and inc["rejected_slip"] == 0 and inc["spanning_true_slip"] == 0
    assert v2["final_error_m"]["iono_zenith"] < v1["final_error_m"]["iono_zenith"]
    assert v2["time_to_1m_s"] < v1["time_to_1m_s"]
    assert np.sum(np.isinf(v2["time_to_1m_s_per_trial"])) <= np.sum(np.isinf(v1["time_to_1m_s_per_trial"]))


@pytest.mark.parametrize("which", ["no_slips", "slips"])
def test_iono_tropo_block_nees_is_consistent(runs, slip_run, which):
    r = runs[1] if which == "no_slips" else slip_run
    lo, hi = _nees_band()
    nees_window = 2.0 * r["anees"]
    assert lo < nees_window < hi, nees_window
    t = np.asarray(r["t_s"])
    assert np.all(np.asarray(r["nees_atmo_mean"])[t > 60.0] < 3.0 * hi)
    assert r["final_error_m"]["iono_zenith"] < 2.0 and r["final_error_m"]["tropo_zenith"] < 1.0


def test_increments_spanning_a_slip_are_not_used(slip_run):
    inc = slip_run["increments"]
    assert inc["detector_slips"] > 0
    assert inc["spanning_true_slip"] > 0
    assert inc["rejected_slip"] >= inc["spanning_true_slip"]
    assert inc["used_spanning_true_slip"] == 0
    assert inc["used"] + inc["rejected_slip"] == inc["candidates"]
    assert inc["used"] > 0


def test_detector_gets_phase_and_doppler_only(monkeypatch):
    calls = []
    real = seed000.CycleSlipDetector.update

    def update(self, *a, **kw):
        calls.append((a, kw))
        return real(self, *a, **kw)

    monkeypatch.setattr(seed000.CycleSlipDetector, "update", update)
    run_streamed(IonoTropoScenario(duration_s=1.0, cmc_window_s=0.5), 2, seed=1, variant=2)
    assert len(calls) == 11
    for a, kw in calls:
        assert len(a) == 3 and not kw  # (t, phase, prr): no lock_count, no expected_m


def test_bad_variant_and_window_raise():
    with pytest.raises(ValueError, match="variant"):
        run_streamed(IonoTropoScenario(duration_s=1.0), 1, seed=0, variant=4)
    with pytest.raises(ValueError, match="cmc_window_s"):
        IonoTropoScenario(duration_s=10.0, cmc_window_s=0.05)
