"""Cycle-slip detector (filters.cycleslip) against the real receiver generator (seed 000)."""
import numpy as np
import pytest

from filters.cycleslip import (CycleSlipConfig, CycleSlipDetector, CycleSlipState, init_state,
                               slip_free, step)
from sitl.constants import F_GPS_L1_HZ, glonass_l1_hz
from sitl.gnss.clock import ClockModel
from sitl.gnss.receiver import Receiver, ReceiverConfig

K_GLO = np.array([-7, -3, 0, 4, 6])
IS_GPS = np.r_[np.ones(7, bool), np.zeros(K_GLO.size, bool)]
CARRIER_HZ = np.r_[np.full(7, F_GPS_L1_HZ), glonass_l1_hz(K_GLO)]
S = IS_GPS.size
T = 0.1
RX_CFG = ReceiverConfig()  # sigma_prr_m_s = 0.064, sigma_phase_m = 0.003 (seed 000)
assert RX_CFG.sigma_prr_m_s == 0.064 and RX_CFG.sigma_phase_m == 0.003


class Geometry:
    """Smooth synthetic (*batch, S) geometry of a manoeuvring receiver.

    Range rate  Ṙ = v0 + A sin(ω t + φ): v0 in ±780 m/s (satellite + vehicle), A up to 30 m/s
    at ω up to 0.8 rad/s (accelerations up to 24 m/s², jerk up to 19 m/s³). Elevations move at
    a GNSS satellite's ±1.45e-4 rad/s, several satellites starting at 6° (largest troposphere
    rate, which the Doppler does not contain).
    """

    def __init__(self, rng, batch):
        shape = (*batch, S)
        self.r0 = rng.uniform(1.95e7, 2.5e7, shape)
        self.v0 = rng.uniform(-780.0, 780.0, shape)
        self.a = rng.uniform(0.0, 30.0, shape)
        self.w = rng.uniform(0.2, 0.8, shape)
        self.phi = rng.uniform(0.0, 2 * np.pi, shape)
        el0 = rng.uniform(np.deg2rad(6.0), np.deg2rad(80.0), shape)
        el0[..., :3] = np.deg2rad(6.0)
        self.el0 = el0
        self.el_rate = rng.choice([-1.0, 1.0], shape) * 1.45e-4
        self.el_rate[..., :3] = 1.45e-4  # low satellites rising: stay above the 5° mask

    def __call__(self, t, el_override=None):
        r = (self.r0 + self.v0 * t - self.a / self.w * (np.cos(self.w * t + self.phi) - np.cos(self.phi)))
        rdot = self.v0 + self.a * np.sin(self.w * t + self.phi)
        el = self.el0 + self.el_rate * t
        if el_override is not None:
            el = el_override(t, el)
        return r, rdot, el


def simulate(seed, batch, n_epochs, slip_prob=0.0, det_config=None, el_override=None, use_lock_count=False):
    """Run Receiver + detector; returns dict of (n_epochs, *batch, S) arrays."""
    rng = np.random.default_rng(seed)
    geo = Geometry(rng, batch)
    rx = Receiver(S, RX_CFG, batch)
    det = CycleSlipDetector((*batch, S), det_config)
    bias, drift = ClockModel().simulate(rng, n_epochs, T, bias0_m=3.0e4, drift0_m_s=rng.uniform(-50, 50, batch),
                                        batch_shape=batch)
    out = {k: [] for k in ("truth", "flag", "tested", "stat", "cycles", "reset")}
    for k in range(n_epochs):
        t = 1000.0 + k * T
        injected = np.zeros((*batch, S), dtype=np.int64)
        if slip_prob > 0.0 and k > 0:
            occurs = rng.random((*batch, S)) < slip_prob
            size = rng.integers(1, 5, size=(*batch, S), endpoint=True)
            sign = rng.choice([-1, 1], size=(*batch, S))
            injected = np.where(occurs, sign * size, 0)
            for j in range(S):
                rx.inject_slip(j, injected[..., j])
        r, rdot, el = geo(t - 1000.0, el_override)
        obs = rx.step(rng, t, r, rdot, el, CARRIER_HZ, IS_GPS, bias[..., k], drift[..., k])
        res = det.update(t, obs.carrier_phase_m, obs.pseudorange_rate_m_s,
                         lock_count=obs.lock_count if use_lock_count else None)
        out["truth"].append(obs.slip)
        out["cycles"].append(np.where(obs.slip, injected, 0))
        out["flag"].append(res.slip)
        out["tested"].append(res.tested)
        out["stat"].append(res.statistic)
        out["reset"].append(res.reset)
    out = {k: np.stack(v) for k, v in out.items()}
    out["detector"] = det
    return out


def scores(out):
    truth, flag, tested = out["truth"], out["flag"], out["tested"]
    n_slip = int(np.sum(truth & tested))
    n_det = int(np.sum(truth & tested & flag))
    n_clean = int(np.sum(~truth & tested))
    n_fa = int(np.sum(~truth & tested & flag))
    one = (np.abs(out["cycles"]) == 1) & tested
    n_one, n_one_det = int(one.sum()), int((one & flag).sum())
    return n_slip, n_det, n_clean, n_fa, n_one, n_one_det


def test_detection_probability_with_real_receiver():
    out = simulate(seed=20240601, batch=(10,), n_epochs=200, slip_prob=0.05)
    n_slip, n_det, n_clean, n_fa, n_one, n_one_det = scores(out)
    pd, pfa = n_det / n_slip, n_fa / max(n_clean, 1)
    print(f"\n[cycleslip] Pd = {n_det}/{n_slip} = {pd:.4f} (1-cycle: {n_one_det}/{n_one}); "
          f"Pfa (clean epochs in the slipping run) = {n_fa}/{n_clean} = {pfa:.2e}")
    assert n_slip >= 1000 and n_one >= 150
    assert pd >= 0.99
    assert n_one_det / n_one >= 0.99
    assert pfa <= 0.01


def test_false_alarms_slip_free_with_real_receiver():
    out = simulate(seed=7, batch=(10,), n_epochs=200)
    n_slip, n_det, n_clean, n_fa, _, _ = scores(out)
    stat = np.concatenate([s[np.isfinite(s)] for s in out["stat"]])
    print(f"\n[cycleslip] slip-free: Pfa = {n_fa}/{n_clean} = {n_fa / n_clean:.2e}; "
          f"statistic mean {stat.mean():+.3f}, std {stat.std():.3f} (model-bounded, expect < 1), "
          f"max |stat| {np.abs(stat).max():.2f} vs k = {CycleSlipConfig().k_sigma:.2f}")
    assert n_slip == 0 and n_clean >= 10_000
    assert n_fa / n_clean <= 0.01
    # every satellite stayed tracked: arcs are the whole 19.9 s run, none reset/flagged
    det = out["detector"]
    assert np.all(slip_free(det.state, 19.9 - 1e-6))
    assert not np.any(slip_free(det.state, 20.5))


def test_crippled_detector_fails_targets():
    # threshold 10x too large: 1- and 2-cycle slips are missed -> Pd target fails
    k = CycleSlipConfig().k_sigma
    out = simulate(seed=20240601, batch=(10,), n_epochs=200, slip_prob=0.05,
                   det_config=CycleSlipConfig(threshold_sigma=10 * k))
    n_slip, n_det, _, _, n_one, n_one_det = scores(out)
    print(f"\n[cycleslip] crippled (10x threshold): Pd = {n_det}/{n_slip} = {n_det / n_slip:.3f}, "
          f"1-cycle {n_one_det}/{n_one}")
    assert n_det / n_slip < 0.99 and n_one_det / n_one < 0.5
    # noise model 10x too optimistic and no model allowance: false alarms exceed 1 %
    out = simulate(seed=7, batch=(10,), n_epochs=200,
                   det_config=CycleSlipConfig(sigma_prr_m_s=0.0064, sigma_phase_m=0.0003, sigma_model_m_s=0.0))
    _, _, n_clean, n_fa, _, _ = scores(out)
    print(f"[cycleslip] crippled (sigmas / 10): Pfa = {n_fa}/{n_clean} = {n_fa / n_clean:.3f}")
    assert n_fa / n_clean > 0.01


def test_loss_of_lock_and_reacquisition_reset_without_flag():
    # satellite 5 drops below the mask for 1 s in the middle of the run and comes back with a
    # fresh ambiguity (a jump of up to 1e6 cycles): no flag, arc restarts at reacquisition.
    def el_override(t, el):
        el = np.array(el)
        if 5.0 <= t < 6.0:
            el[..., 5] = np.deg2rad(2.0)
        return el

    for use_lc in (False, True):
        out = simulate(seed=3, batch=(4,), n_epochs=150, el_override=el_override, use_lock_count=use_lc)
        assert not np.any(out["flag"])
        assert not np.any(out["tested"][50:60, :, 5])  # untracked
        assert np.all(out["reset"][60, :, 5]) and not np.any(out["tested"][60, :, 5])
        assert np.all(out["tested"][61:, :, 5])
        det = out["detector"]
        since = det.state.slip_free_since_s
        assert np.allclose(since[:, 5], 1006.0) and np.allclose(np.delete(since, 5, axis=-1), 1000.0)
        sf = det.slip_free(9.0)  # last epoch t = 1014.9
        assert np.all(sf[:, 5] == False) and np.all(np.delete(sf, 5, axis=-1))  # noqa: E712
        assert np.all(det.slip_free(8.9)[:, 5])


def test_window_query_restarts_at_detected_slip():
    cfg = CycleSlipConfig()
    st = init_state((2, 3))
    lam = 0.19
    for k in range(20):
        t = k * T
        phase = 100.0 * t + np.zeros((2, 3))
        if k >= 10:
            phase[1, 2] += lam  # one-cycle slip at epoch 10, batch 1, satellite 2
        st, res = step(cfg, st, t, phase, np.full((2, 3), 100.0))
        if k == 10:
            assert res.slip[1, 2] and res.slip.sum() == 1
        elif k > 0:
            assert not res.slip.any() and res.tested.all()
    assert np.isclose(st.slip_free_since_s[1, 2], 1.0) and np.allclose(st.slip_free_since_s[0], 0.0)
    assert slip_free(st, 0.9)[1, 2] and not slip_free(st, 1.0)[1, 2] and slip_free(st, 1.9)[0].all()
    # NaN clears the satellite
    nan_phase = np.full((2, 3), 5.0)
    nan_phase[0, 0] = np.nan
    st, res = step(cfg, st, 2.0, nan_phase, np.full((2, 3), 100.0))
    assert np.isnan(st.slip_free_since_s[0, 0]) and not slip_free(st, 0.0)[0, 0]
    assert not res.tested[0, 0] and not res.slip[0, 0]


def test_threshold_derivation():
    cfg = CycleSlipConfig()
    s = cfg.residual_sigma_m(0.1)
    assert np.isclose(s, np.sqrt(2 * 0.003**2 + 0.5 * (0.1 * 0.064) ** 2 + (0.05 * 0.1) ** 2))
    assert np.isclose(cfg.k_sigma, 4.891638, atol=1e-5)  # Φ⁻¹(1 − 0.5e-6)
    assert 0.19 - cfg.k_sigma * s > 18 * s  # a one-cycle slip clears the threshold by > 18 σ


@pytest.mark.parametrize("kwargs,name", [
    (dict(sigma_prr_m_s=-1.0), "sigma_prr_m_s"),
    (dict(sigma_phase_m=np.nan), "sigma_phase_m"),
    (dict(pfa=0.0), "pfa"),
    (dict(pfa=1.5), "pfa"),
    (dict(threshold_sigma=-2.0), "threshold_sigma"),
    (dict(max_dt_s=0.0), "max_dt_s"),
    (dict(sigma_model_m_s="x"), "sigma_model_m_s"),
])
def test_bad_config_raises(kwargs, name):
    with pytest.raises(ValueError, match=name):
        CycleSlipConfig(**kwargs)


def test_bad_step_input_raises():
    cfg = CycleSlipConfig()
    st = init_state((2, 3))
    ok = np.zeros((2, 3))
    with pytest.raises(ValueError, match="phase_m"):
        step(cfg, st, 0.0, np.zeros((2, 4)), ok)
    with pytest.raises(ValueError, match="prr_m_s"):
        step(cfg, st, 0.0, ok, np.full((2, 3), np.inf))
    with pytest.raises(ValueError, match="t_s"):
        step(cfg, st, np.nan, ok, ok)
    with pytest.raises(ValueError, match="lock_count"):
        step(cfg, st, 0.0, ok, ok, lock_count=np.full((2, 3), 0.5))
    with pytest.raises(ValueError, match="expected_m"):
        step(cfg, st, 0.0, ok, ok, expected_m=np.zeros(5))
    with pytest.raises(ValueError, match="config"):
        step(None, st, 0.0, ok, ok)
    with pytest.raises(ValueError, match="state"):
        step(cfg, None, 0.0, ok, ok)
    st1, _ = step(cfg, st, 1.0, ok, ok)
    with pytest.raises(ValueError, match="t_s"):
        step(cfg, st1, 1.0, ok, ok)
    with pytest.raises(ValueError, match="shape"):
        init_state(())
    with pytest.raises(ValueError, match="window_s"):
        slip_free(st1, -1.0)
    with pytest.raises(ValueError, match="t_s"):
        slip_free(st, 1.0)  # no epoch processed yet
    assert isinstance(st1, CycleSlipState)
