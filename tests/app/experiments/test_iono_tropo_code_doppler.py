"""Seed 000 variant 1 (pseudorange + pseudorange rate): the batched Monte Carlo library run."""
import inspect

import numpy as np
import pytest
import scipy.stats

from sitl.app.experiments import iono_tropo_filters
from sitl.app.experiments.iono_tropo_filters import IonoTropoScenario, run_code_doppler

TRIALS = 8


@pytest.fixture(scope="module")
def short_run():
    return run_code_doppler(IonoTropoScenario(duration_s=300.0), TRIALS, seed=7)


@pytest.mark.slow
def test_iono_tropo_errors_shrink_from_the_prior(short_run):
    r = short_run
    assert r["n_visible_min"] >= 12  # the seed's "at least 12 satellites in view"
    for key, prior in (("iono_err_rms_m", r["prior_error"]["iono_rms_m"]),
                       ("tropo_err_rms_m", r["prior_error"]["tropo_rms_m"])):
        series = np.asarray(r[key])
        assert np.all(np.isfinite(series))
        # RMS over trials at the end is below a third of the prior error and of the error
        # after the first update
        assert series[-1] < prior / 3.0, (key, series[-1], prior)
        assert series[-1] < series[0] / 3.0, (key, series[-1], series[0])
    assert r["final_error_m"]["iono_zenith"] < 2.0
    assert r["final_error_m"]["tropo_zenith"] < 1.0


@pytest.mark.slow
def test_iono_tropo_block_nees_is_chi_square_consistent(short_run):
    """Mean over the 8 trials of the (I_g, U_g) NEES, averaged over the last 60 s, against
    the two-sided 99.9 % band of (1/8) chi2(2 * 8): about [0.44, 5.16] (per dof
    [0.22, 2.58]). Loose on purpose: the epochs of the window are strongly correlated, so
    they add few independent samples, and the simulator's geodetic elevation in the
    mapping functions differs slightly from the filter's geocentric eq 10."""
    lo = scipy.stats.chi2.ppf(0.0005, 2 * TRIALS) / TRIALS
    hi = scipy.stats.chi2.ppf(0.9995, 2 * TRIALS) / TRIALS
    assert 0.43 < lo < 0.45 and 5.1 < hi < 5.2
    nees_window = 2.0 * short_run["anees"]
    assert lo < nees_window < hi, nees_window
    # and at every epoch after the first minute the per-epoch mean stays below a very loose cap
    t = np.asarray(short_run["t_s"])
    assert np.all(np.asarray(short_run["nees_atmo_mean"])[t > 60.0] < 3.0 * hi)


@pytest.mark.slow
def test_time_to_1m_is_defined_per_trial(short_run):
    ttm = np.asarray(short_run["time_to_1m_s_per_trial"])
    assert ttm.shape == (TRIALS,)
    assert np.all((ttm >= 0.0) & ((ttm <= 300.0) | np.isinf(ttm)))
    assert short_run["time_to_1m_s"] == pytest.approx(float(np.median(ttm)))


def test_the_filter_never_sees_truth(monkeypatch):
    # the public entry point takes only the scenario, the trial count, the seed and options
    assert list(inspect.signature(run_code_doppler).parameters) == ["scn", "trials", "seed", "progress", "backend"]
    # spy: the filter's measurement model holds exactly the satellite states computed by
    # ephemeris_for_filter from the receiver's own outputs (the tracked satellites' columns,
    # with the matching sub-constellation) and the filter's clock estimate
    outputs, ephem_calls, models = [], [], []
    real_step = iono_tropo_filters.Receiver.step

    def step(self, *a, **kw):
        obs = real_step(self, *a, **kw)
        outputs.append(obs)
        return obs

    real_model = iono_tropo_filters.IonoTropoGnss

    def model(*a, **kw):
        m = real_model(*a, **kw)
        models.append(m)
        return m

    monkeypatch.setattr(iono_tropo_filters.Receiver, "step", step)
    monkeypatch.setattr(iono_tropo_filters, "ephemeris_for_filter",
                        lambda t, pr, const, **kw: _spy(ephem_calls, outputs, t, pr, const, **kw))
    monkeypatch.setattr(iono_tropo_filters, "IonoTropoGnss", model)
    run_code_doppler(IonoTropoScenario(duration_s=1.0), 2, seed=1)
    assert len(models) == len(ephem_calls) == len(outputs) == 11
    for m, (sp, sv), obs in zip(models, ephem_calls, outputs):
        np.testing.assert_array_equal(m.sat_pos_ecef_m, sp)
        np.testing.assert_array_equal(m.sat_vel_ecef_m_s, sv)


def _spy(calls, outputs, t, pr, const, **kw):
    from sitl.gnss import world

    assert set(kw) == {"pseudorange_rate_m_s", "clock_bias_est_m"}
    obs = outputs[-1]
    vis = obs.visible[0]
    np.testing.assert_array_equal(pr, obs.pseudorange_m[:, vis])  # the receiver's numbers, tracked only
    np.testing.assert_array_equal(kw["pseudorange_rate_m_s"], obs.pseudorange_rate_m_s[:, vis])
    assert list(const.sat_id) == list(IonoTropoScenario(duration_s=1.0).constellation().sat_id[vis])
    out = world.ephemeris_for_filter(t, pr, const, **kw)
    calls.append(out)
    return out


@pytest.mark.parametrize("kw, name", [
    ({"el_mask_deg": 89.0}, "el_mask_deg"),  # fewer than 4 satellites in view
    ({"el_mask_deg": 0.0}, "el_mask_deg"),
    ({"sigma_pr_m": -6.0}, "sigma_pr_m"),
    ({"sigma_prr_m_s": 0.0}, "sigma_prr_m_s"),
    ({"dt_s": float("nan")}, "dt_s"),
    ({"duration_s": -1.0}, "duration_s"),
    ({"sigma0_iono_m": -20.0}, "sigma0_iono_m"),
    ({"iono_zenith_m": -15.0}, "iono_zenith_m"),
])
def test_bad_scenario_values_raise_naming_the_parameter(kw, name):
    with pytest.raises(ValueError, match=name):
        IonoTropoScenario(**kw)


def test_bad_trials_raise():
    with pytest.raises(ValueError, match="trials"):
        run_code_doppler(IonoTropoScenario(duration_s=1.0), 0, seed=1)
