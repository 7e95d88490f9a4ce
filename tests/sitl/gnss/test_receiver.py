"""Receiver measurement generator (seed 000, eqs. 9, 11, 18-22, 35)."""
import numpy as np
import pytest
from scipy import stats

from sitl.constants import C_M_S, F_GPS_L1_HZ, glonass_l1_hz
from sitl.gnss.atmosphere import iono_slant_delay_m, tropo_slant_delay_m
from sitl.gnss.receiver import Observation, Receiver, ReceiverConfig
from tests.helpers import chi2_ok

K_GLO = np.array([-7, -3, 0, 6])
IS_GPS = np.r_[np.ones(6, bool), np.zeros(K_GLO.size, bool)]
CARRIER_HZ = np.r_[np.full(6, F_GPS_L1_HZ), glonass_l1_hz(K_GLO)]
S = IS_GPS.size
EL_RAD = np.deg2rad(np.linspace(10.0, 80.0, S))
T = 0.1


def geometry(batch, t):
    """Synthetic (*batch, S) ranges, range rates and elevations at time t."""
    rate = np.linspace(-800.0, 800.0, S)
    rng_m = 2.2e7 + 1e5 * np.arange(S) + rate * t
    shape = (*batch, S)
    return (np.broadcast_to(rng_m, shape), np.broadcast_to(rate, shape), np.broadcast_to(EL_RAD, shape))


def run(cfg, n_epochs, batch=(), seed=0, el_fn=None, clock=(100.0, 0.3), before_step=None):
    rx = Receiver(S, cfg, batch)
    rng = np.random.default_rng(seed)
    obs = []
    for i in range(n_epochs):
        t = 1000.0 + i * T
        r, rr, el = geometry(batch, t)
        if el_fn is not None:
            el = el_fn(i, el)
        if before_step is not None:
            before_step(i, rx)
        bias = np.full(batch, clock[0] + clock[1] * (t - 1000.0))
        obs.append(rx.step(rng, t, r, rr, el, CARRIER_HZ, IS_GPS, bias, np.full(batch, clock[1])))
    return rx, obs


def truth_terms(o, batch, cfg, clock=(100.0, 0.3)):
    r, rr, _ = geometry(batch, o.t_gps_s)
    el = o.el_rad
    bias = clock[0] + clock[1] * (o.t_gps_s - 1000.0)
    offset = np.where(IS_GPS, cfg.gps_glonass_offset_m, 0.0)
    iono = iono_slant_delay_m(cfg.iono_zenith_m, el, CARRIER_HZ)
    tropo = tropo_slant_delay_m(cfg.tropo_zenith_m, el)
    return r, rr, bias, offset, iono, tropo


def test_noise_levels_match_sigmas_and_wrong_sigmas_fail():
    cfg = ReceiverConfig(gps_glonass_offset_m=37.0)
    batch = (400,)
    _, obs = run(cfg, 5, batch, seed=11)
    e_pr, e_prr, e_ph = [], [], []
    for o in obs:
        r, rr, bias, offset, iono, tropo = truth_terms(o, batch, cfg)
        np.testing.assert_allclose(o.iono_slant_m, iono, rtol=1e-12)
        np.testing.assert_allclose(o.tropo_slant_m, tropo, rtol=1e-12)
        e_pr.append(o.pseudorange_m - r - bias - offset - tropo - iono)
        e_prr.append(o.pseudorange_rate_m_s - rr - 0.3)
        e_ph.append(o.carrier_phase_m - r - bias - offset - tropo + iono - o.wavelength_m * o.ambiguity_cycles)
    for e, sigma in ((e_pr, cfg.sigma_pr_m), (e_prr, cfg.sigma_prr_m_s), (e_ph, cfg.sigma_phase_m)):
        e = np.asarray(e)
        assert e.size == 5 * 400 * S and np.all(np.isfinite(e))
        assert chi2_ok(e, sigma)
        assert not chi2_ok(e, 1.05 * sigma) and not chi2_ok(e, sigma / 1.05)
        assert abs(e.mean()) < 4 * sigma / np.sqrt(e.size)


def test_code_minus_carrier_is_twice_iono_minus_ambiguity():
    cfg = ReceiverConfig()
    batch = (300,)
    _, obs = run(cfg, 3, batch, seed=5)
    for o in obs:
        cmc = o.pseudorange_m - o.carrier_phase_m
        resid = cmc - (2.0 * o.iono_slant_m - o.wavelength_m * o.ambiguity_cycles)
        assert chi2_ok(resid, np.hypot(cfg.sigma_pr_m, cfg.sigma_phase_m))
        # GPS L1 is below every GLONASS L1 carrier, so at equal elevation it is delayed most
        assert np.all(o.iono_slant_m[..., IS_GPS] > iono_slant_delay_m(15.0, EL_RAD[IS_GPS], glonass_l1_hz(-7)))


def test_noise_free_measurements_are_exact():
    cfg = ReceiverConfig(sigma_pr_m=0, sigma_prr_m_s=0, sigma_phase_m=0, gps_glonass_offset_m=-12.5)
    _, obs = run(cfg, 2)
    o = obs[-1]
    r, rr, bias, offset, iono, tropo = truth_terms(o, (), cfg)
    np.testing.assert_allclose(o.pseudorange_m, r + bias + offset + tropo + iono, rtol=0, atol=1e-7)
    np.testing.assert_allclose(o.pseudorange_rate_m_s, rr + 0.3, rtol=0, atol=1e-12)
    phase = r + bias + offset + tropo - iono + o.wavelength_m * o.ambiguity_cycles
    np.testing.assert_allclose(o.carrier_phase_m, phase, rtol=0, atol=1e-7)
    np.testing.assert_allclose(o.carrier_phase_cycles, phase / (C_M_S / CARRIER_HZ), rtol=1e-15)
    np.testing.assert_allclose(o.wavelength_m, C_M_S / CARRIER_HZ)
    assert np.all(np.abs(o.ambiguity_cycles) <= cfg.ambiguity_max_cycles)
    # Δ_A only on GPS
    assert np.all(offset[IS_GPS] == -12.5) and np.all(offset[~IS_GPS] == 0.0)


def estimated_ambiguity(o, batch, cfg):
    """N from the phase with the truth terms removed (noise 3 mm ≪ λ/2 ≈ 9.5 cm)."""
    r, rr, bias, offset, iono, tropo = truth_terms(o, batch, cfg)
    return np.round((o.carrier_phase_m - r - bias - offset - tropo + iono) / o.wavelength_m)


def test_ambiguity_constant_while_locked_without_slips():
    cfg = ReceiverConfig()
    batch = (20,)
    rx, obs = run(cfg, 60, batch, seed=2)
    n = np.array([estimated_ambiguity(o, batch, cfg) for o in obs])
    np.testing.assert_array_equal(n, np.broadcast_to(n[0], n.shape))
    np.testing.assert_array_equal(n[-1], obs[-1].ambiguity_cycles)
    assert len(np.unique(n[0])) > S  # independent draws per trial and satellite
    assert not any(o.slip.any() for o in obs)
    np.testing.assert_array_equal([o.lock_count[0, 0] for o in obs], np.arange(60))
    assert np.all(rx.slip_count == 0)


def test_random_slips_change_ambiguity_only_at_flagged_epochs():
    cfg = ReceiverConfig(cycle_slip_rate_hz=0.5, slip_cycles_max=3)  # p = 0.05 per epoch
    batch = (50,)
    rx, obs = run(cfg, 80, batch, seed=9)
    n = np.array([estimated_ambiguity(o, batch, cfg) for o in obs])
    slip = np.array([o.slip for o in obs])
    dn = np.diff(n, axis=0)
    np.testing.assert_array_equal(dn != 0, slip[1:])
    assert not slip[0].any()  # no slip at acquisition
    assert 1 <= np.abs(dn[slip[1:]]).min() and np.abs(dn[slip[1:]]).max() <= 3
    # slip count is binomial(79·50·S, 0.05): inside a 99.9 % interval
    n_trials = 79 * 50 * S
    lo, hi = stats.binom.ppf([0.0005, 0.9995], n_trials, 0.05)
    assert lo <= slip.sum() <= hi
    np.testing.assert_array_equal(rx.slip_count, slip.sum(axis=0))
    # lock count restarts at the slip
    lc = np.array([o.lock_count for o in obs])
    assert np.all(lc[slip] == 0)
    assert np.all(lc[1:][~slip[1:]] == lc[:-1][~slip[1:]] + 1)


def test_satellite_crossing_the_mask_gets_a_new_ambiguity():
    cfg = ReceiverConfig()
    mask = cfg.el_mask_rad
    j = 3
    # elevation of satellite j: above the mask, sets at epoch 10, rises again at epoch 20
    ramp = mask + np.deg2rad(0.5) * np.abs(np.arange(40) - 15.0) - np.deg2rad(2.4)

    def el_fn(i, el):
        el = np.array(el)
        el[..., j] = ramp[i]
        return el

    batch = (4,)
    _, obs = run(cfg, 40, batch, seed=3, el_fn=el_fn)
    vis = np.array([o.visible[:, j] for o in obs])
    expected = ramp >= mask
    np.testing.assert_array_equal(vis, np.broadcast_to(expected[:, None], vis.shape))
    down = np.flatnonzero(~expected)
    assert down[0] == 11 and down[-1] == 19
    for o in obs[11:20]:
        assert np.all(np.isnan(o.pseudorange_m[:, j])) and np.all(np.isnan(o.carrier_phase_m[:, j]))
        assert np.all(np.isnan(o.pseudorange_rate_m_s[:, j])) and np.all(o.lock_count[:, j] == -1)
        assert np.all(np.isfinite(o.pseudorange_m[:, np.arange(S) != j]))
    n_before, n_after = obs[10].ambiguity_cycles[:, j], obs[20].ambiguity_cycles[:, j]
    assert np.all(n_before != n_after)
    assert np.all(obs[20].lock_count[:, j] == 0) and not obs[20].slip.any()
    np.testing.assert_array_equal(obs[39].ambiguity_cycles[:, j], n_after)
    n_est = np.array([estimated_ambiguity(o, batch, cfg)[:, j] for o in obs[20:]])
    np.testing.assert_array_equal(n_est, np.broadcast_to(n_after, n_est.shape))
    # other satellites keep theirs
    np.testing.assert_array_equal(obs[39].ambiguity_cycles[:, :j], obs[0].ambiguity_cycles[:, :j])


def test_injected_slip_is_an_integer_number_of_wavelengths():
    cfg = ReceiverConfig()
    batch = (3,)
    j = 7  # GLONASS channel 0

    def before_step(i, rx):
        if i == 5:
            rx.inject_slip(j, [4, -2, 0])

    _, obs = run(cfg, 8, batch, seed=4, before_step=before_step)
    d_phase = obs[5].carrier_phase_m[:, j] - obs[4].carrier_phase_m[:, j]
    def geom_plus_clock(o):
        r, _, bias, _, _, _ = truth_terms(o, batch, cfg)
        return r[:, j] + bias

    d_geom = geom_plus_clock(obs[5]) - geom_plus_clock(obs[4])  # elevation is constant here
    cycles = (d_phase - d_geom) / obs[5].wavelength_m[j]
    np.testing.assert_allclose(cycles, [4, -2, 0], atol=0.1)
    np.testing.assert_array_equal(obs[5].ambiguity_cycles[:, j] - obs[4].ambiguity_cycles[:, j], [4, -2, 0])
    np.testing.assert_array_equal(obs[5].slip[:, j], [True, True, False])
    assert obs[5].slip.sum() == 2 and not obs[6].slip.any()
    np.testing.assert_array_equal(obs[5].lock_count[:, j], [0, 0, 5])
    # the code is not affected by a carrier slip
    d_pr = obs[5].pseudorange_m[:, j] - obs[4].pseudorange_m[:, j] - d_geom
    assert np.all(np.abs(d_pr) < 6 * np.sqrt(2) * cfg.sigma_pr_m)


def test_shapes_nan_masking_and_determinism():
    cfg = ReceiverConfig()
    batch = (2, 3)
    el_fn = lambda i, el: np.where(np.arange(S) % 2 == 0, el, np.deg2rad(-10.0))
    _, obs1 = run(cfg, 2, batch, seed=8, el_fn=el_fn)
    _, obs2 = run(cfg, 2, batch, seed=8, el_fn=el_fn)
    o = obs1[-1]
    assert isinstance(o, Observation) and o.pseudorange_m.shape == (2, 3, S) and o.wavelength_m.shape == (S,)
    for name in ("pseudorange_m", "pseudorange_rate_m_s", "carrier_phase_m", "carrier_phase_cycles",
                 "ambiguity_cycles", "iono_slant_m", "tropo_slant_m"):
        a = getattr(o, name)
        assert np.all(np.isnan(a[..., 1::2])) and np.all(np.isfinite(a[..., ::2])), name
        np.testing.assert_array_equal(a, getattr(obs2[-1], name))
    assert o.visible.dtype == bool and o.slip.dtype == bool


def test_invalid_inputs_raise_value_error():
    with pytest.raises(ValueError, match="sigma_pr_m"):
        ReceiverConfig(sigma_pr_m=-1.0)
    with pytest.raises(ValueError, match="sigma_phase_m"):
        ReceiverConfig(sigma_phase_m=np.nan)
    with pytest.raises(ValueError, match="el_mask_rad"):
        ReceiverConfig(el_mask_rad=0.0)
    with pytest.raises(ValueError, match="slip_cycles_max"):
        ReceiverConfig(slip_cycles_max=0)
    with pytest.raises(ValueError, match="cycle_slip_rate_hz"):
        ReceiverConfig(cycle_slip_rate_hz=-0.1)
    rx = Receiver(S, ReceiverConfig(cycle_slip_rate_hz=20.0))
    r, rr, el = geometry((), 0.0)
    rng = np.random.default_rng(0)
    rx.step(rng, 0.0, r, rr, el, CARRIER_HZ, IS_GPS, 0.0, 0.0)
    with pytest.raises(ValueError, match="cycle_slip_rate_hz"):
        rx.step(rng, 0.1, r, rr, el, CARRIER_HZ, IS_GPS, 0.0, 0.0)  # p = 2 > 1
    with pytest.raises(ValueError, match="t_gps_s"):
        rx.step(rng, 0.0, r, rr, el, CARRIER_HZ, IS_GPS, 0.0, 0.0)
    with pytest.raises(ValueError, match="range_m"):
        rx.step(rng, 1.0, r[:3], rr, el, CARRIER_HZ, IS_GPS, 0.0, 0.0)
    with pytest.raises(ValueError, match="sat_index"):
        rx.inject_slip(S, 1)
    with pytest.raises(ValueError, match="cycles"):
        rx.inject_slip(0, 0.5)
