"""Scoring of the seed 003 integrity run (the truth side): detection bookkeeping per monitored
filter (Pd per fault kind, Pfa with exact intervals, delays, the open-loop ROC), the ramp
detection bound of an oracle that knows the onset, and the targets."""
from __future__ import annotations

import math

import numpy as np
import scipy.stats

from sitl.app.experiments.integrity.scenario import IntegrityScenario

__all__ = ["TARGETS", "J_GRID", "W_GRID", "ramp_signature", "ramp_oracle_pd"]

TARGETS = {"pd_min": 0.99, "pfa_max": 0.003, "rmse_ratio_adaptive_robust_min": 2.0,
           "rmse_ratio_with_bias_estimation_about": 10.0}

J_GRID = np.linspace(0.0, 12.0, 601)  # thresholds on |beta|
W_GRID = np.logspace(-2, 4, 601)  # thresholds on the normalised window statistic (1 = operating point)


class _Score:
    """Detection bookkeeping of one monitored filter (scoring side: uses the injected truth)."""

    def __init__(self, scn, trials, S, truth):
        self.scn, self.N, self.S, self.tr = scn, trials, S, truth
        self.rows = np.arange(trials)
        self.n_healthy = 0
        self.n_fa = 0
        self.h_j = np.zeros(J_GRID.size, dtype=np.int64)  # healthy counts with stat > threshold
        self.h_w = np.zeros(W_GRID.size, dtype=np.int64)
        self.step_hit = np.zeros(trials, dtype=bool)
        self.step_stat = np.zeros(trials)
        self.step_first = np.full(trials, -1)
        self.ramp_hit = np.zeros(trials, dtype=bool)
        self.ramp_stat = np.zeros(trials)
        self.ramp_first = np.full(trials, -1)
        self.out_n = 0
        self.out_hit = 0
        self.out_stats = []
        self.out_first_k = []
        self.step_valid = np.ones(trials, dtype=bool)
        self.ramp_valid = np.ones(trials, dtype=bool)

    def epoch(self, k, rep, count, healthy, out_mask, missing_ch):
        scn, S = self.scn, self.S
        cfg_thr_b = scipy.stats.chi2.isf(scn.bias_alpha, 1)
        thr_ms = scipy.stats.chi2.isf(scn.window_alpha, count) / count
        alarm_rows = rep.jump | rep.drift
        alarm = alarm_rows[:, :S] | alarm_rows[:, S:]
        ab = np.abs(rep.beta)
        jstat = np.maximum(ab[:, :S], ab[:, S:])
        wr = np.maximum(rep.bias_stat / cfg_thr_b, rep.drift_stat / thr_ms)
        wstat = np.maximum(wr[:, :S], wr[:, S:])
        # healthy channel-epochs
        self.n_healthy += int(healthy.sum())
        self.n_fa += int((alarm & healthy).sum())
        self.h_j += np.searchsorted(np.sort(jstat[healthy]), J_GRID, side="right").astype(np.int64) * -1 \
            + int(healthy.sum())
        self.h_w += np.searchsorted(np.sort(wstat[healthy]), W_GRID, side="right").astype(np.int64) * -1 \
            + int(healthy.sum())
        r = self.rows
        tr = self.tr
        # steps: onset epoch and the next
        c = tr["step_ch"]
        for d in (0, 1):
            at = tr["step_k0"] + d == k
            if at.any():
                miss = missing_ch[r[at], c[at]]
                if d == 0:
                    self.step_valid[at] &= ~miss
                self.step_hit[at] |= alarm[r[at], c[at]]
                self.step_stat[at] = np.maximum(self.step_stat[at], jstat[r[at], c[at]])
        active = (k >= tr["step_k0"]) & (k < tr["step_k1"]) & (self.step_first < 0)
        first = active & alarm[r, c]
        self.step_first[first] = k
        # ramps: within ramp_detect_s of the onset
        c = tr["ramp_ch"]
        kd = round(scn.ramp_detect_s / scn.dt_s)
        win = (k >= tr["ramp_k0"]) & (k <= tr["ramp_k0"] + kd)
        if win.any():
            self.ramp_hit[win] |= alarm[r[win], c[win]]
            self.ramp_stat[win] = np.maximum(self.ramp_stat[win], wstat[r[win], c[win]])
            at0 = tr["ramp_k0"] == k
            self.ramp_valid[at0] &= ~missing_ch[r[at0], c[at0]]
        first = (k >= tr["ramp_k0"]) & (self.ramp_first < 0) & alarm[r, c]
        self.ramp_first[first] = k
        # outliers of >= 5 sigma_ref
        if out_mask.any():
            self.out_n += int(out_mask.sum())
            self.out_hit += int((alarm & out_mask).sum())
            self.out_stats.append(jstat[out_mask])

    def result(self):
        scn = self.scn
        dt = scn.dt_s
        tr = self.tr
        op_j = scn.jump_sigma

        def rate(k, n):
            lo, hi = (scipy.stats.binomtest(k, n).proportion_ci(0.95, method="exact") if n else (math.nan, math.nan))
            return {"value": k / n if n else math.nan, "ci95": [lo, hi], "count": int(k), "of": int(n)}

        sv, rv = self.step_valid, self.ramp_valid
        step_delay = (self.step_first - tr["step_k0"]) * dt
        ramp_delay = (self.ramp_first - tr["ramp_k0"]) * dt
        ds = self.step_hit & sv
        dr = self.ramp_hit & rv
        pfa = rate(self.n_fa, self.n_healthy)
        mag = np.abs(tr["step_mag"]) / scn.sigma_ref_m
        rr = np.abs(tr["ramp_rate"])
        step_bins = [(5.0, 10.0), (10.0, 20.0 + 1e-9)]
        ramp_bins = [(0.5, 1.0), (1.0, 2.0 + 1e-9)]
        out = {
            "step": {"pd": rate(int(ds.sum()), int(sv.sum())), "pfa": pfa,
                     "mean_delay_s": float(np.mean(step_delay[ds])) if ds.any() else None,
                     "by_magnitude_sigma": {f"{a:g}-{min(b, 20):g}": rate(int((ds & (mag >= a) & (mag < b)).sum()),
                                                                          int((sv & (mag >= a) & (mag < b)).sum()))
                                            for a, b in step_bins}},
            "ramp": {"pd": rate(int(dr.sum()), int(rv.sum())), "pfa": pfa,
                     "mean_delay_s": float(np.mean(ramp_delay[dr])) if dr.any() else None,
                     "by_rate_m_s": {f"{a:g}-{min(b, 2):g}": rate(int((dr & (rr >= a) & (rr < b)).sum()),
                                                                  int((rv & (rr >= a) & (rr < b)).sum()))
                                     for a, b in ramp_bins},
                     "detected_ever": rate(int(((self.ramp_first >= 0) & rv).sum()), int(rv.sum()))},
            "outlier": {"pd": rate(self.out_hit, self.out_n), "pfa": pfa, "mean_delay_s": 0.0 if self.out_hit else None},
        }
        # ROC (open loop over the recorded statistics)
        pfa_j = self.h_j / max(self.n_healthy, 1)
        pfa_w = self.h_w / max(self.n_healthy, 1)
        outs = np.concatenate(self.out_stats) if self.out_stats else np.zeros(0)
        roc = {
            "step": {"threshold": J_GRID, "pfa": pfa_j,
                     "pd": (self.step_stat[sv][None, :] > J_GRID[:, None]).mean(axis=1) if sv.any() else None,
                     "operating_threshold": op_j, "statistic": "max |beta| of the channel at onset and onset + 1"},
            "outlier": {"threshold": J_GRID, "pfa": pfa_j,
                        "pd": (outs[None, :] > J_GRID[:, None]).mean(axis=1) if outs.size else None,
                        "operating_threshold": op_j, "statistic": "max |beta| of the channel at the outlier"},
            "ramp": {"threshold": W_GRID, "pfa": pfa_w,
                     "pd": (self.ramp_stat[rv][None, :] > W_GRID[:, None]).mean(axis=1) if rv.any() else None,
                     "operating_threshold": 1.0,
                     "statistic": "max over the first ramp_detect_s of the channel's window statistic / threshold"},
        }
        return out, roc


# ------------------------------------------------------------------ the ramp detection bound
def ramp_signature(sigma_w_m: float, gm_sigma_m: float, gm_tau_s: float, dt_s: float, n: int):
    """What a code-only pseudorange ramp of unit rate (1 m/s, zero at the onset epoch, j dt at the
    j-th epoch after it) does to the innovations of the best filter of that channel's errors:
    the steady-state Kalman filter of the world's error model, white noise ``sigma_w_m`` plus a
    first-order Gauss-Markov error (``gm_sigma_m``, ``gm_tau_s``), run long before the onset.
    Its innovations are white with variance S; the ramp adds the deterministic signature g_j
    (the Willsky-Jones failure signature). Returns (g_j / sqrt(S) for j = 0..n-1, the cumulative
    signal-to-noise ratio sqrt(sum_{i<=j} g_i^2 / S) per unit rate)."""
    import scipy.linalg

    a = math.exp(-dt_s / gm_tau_s)
    q = gm_sigma_m**2 * -math.expm1(-2.0 * dt_s / gm_tau_s)
    r = sigma_w_m**2
    # the prior variance of the filter's steady state: the filtering Riccati equation (the DARE's dual)
    p_prior = float(scipy.linalg.solve_discrete_are(np.array([[a]]), np.array([[1.0]]), np.array([[q]]),
                                                    np.array([[r]]))[0, 0]) if gm_sigma_m > 0 else 0.0
    s = p_prior + r
    k = p_prior / s
    g = np.empty(n)
    est = 0.0  # the filter's estimate of the fault's own contribution (linear: the faulty run minus the healthy one)
    for j in range(n):
        pred = a * est
        g[j] = j * dt_s - pred
        est = pred + k * g[j]
    gn = g / math.sqrt(s)
    return gn, np.sqrt(np.cumsum(gn * gn))


def ramp_oracle_pd(rates_m_s, scn: IntegrityScenario, pfa: float, rng, draws: int = 20_000) -> np.ndarray:
    """Detection probability, within ``scn.ramp_detect_s`` of the onset, of a code-only pseudorange
    ramp of each |rate| in ``rates_m_s``, for an oracle: it knows the faulty channel, the onset
    and everything about the receiver (position, clock, the other satellites), and it has the
    channel's whole history; it does not know the rate or its sign. At every epoch after the onset
    it runs the most powerful test of "a ramp since the onset" against "no fault" on that channel's
    innovations (the matched filter of the failure signature, ramp_signature), two-sided at the
    per-epoch false-alarm probability ``pfa``; it alarms when any of them fires. No detector with less
    knowledge, at that false-alarm rate per epoch, can do better (it only ignores the other
    channels' nuisance, which would lower it). Monte Carlo with common random numbers over the rates."""
    n = int(round(scn.ramp_detect_s / scn.dt_s)) + 1  # the onset epoch (zero) to onset + ramp_detect_s
    gn, snr = ramp_signature(scn.sigma_pr_m, scn.gm_sigma_m, scn.gm_tau_s, scn.dt_s, n)
    live = snr > 0
    e = rng.standard_normal((draws, n))
    z = np.cumsum(e * gn, axis=1)[:, live] / snr[live]  # N(0, 1) per epoch under no fault
    thr = scipy.stats.norm.isf(pfa / 2.0)
    return np.array([float((np.abs(z + abs(float(rt)) * snr[live]) > thr).any(axis=1).mean()) for rt in rates_m_s])


def _ramp_oracle(scn: IntegrityScenario, seed: int, rates: np.ndarray, valid: np.ndarray, pfa: float) -> dict:
    """The oracle's Pd (ramp_oracle_pd) for this run's code-only ramps: overall and per rate bin, the
    mean over the trials of the oracle's Pd at each trial's rate (the same trials as ``ramp.pd``)."""
    grid = np.linspace(scn.ramp_rate_m_s[0], scn.ramp_rate_m_s[1], 61)
    rng = np.random.default_rng(np.random.SeedSequence(seed).spawn(4)[3])  # not one of the run's streams
    pd_grid = ramp_oracle_pd(grid, scn, pfa, rng)
    rr = np.abs(rates)
    per = np.interp(rr, grid, pd_grid)
    bins = [(0.5, 1.0), (1.0, 2.0 + 1e-9)]

    def mean(sel):
        return float(per[sel].mean()) if sel.any() else None

    return {"pd": mean(valid), "by_rate_m_s": {f"{a:g}-{min(b, 2):g}": mean(valid & (rr >= a) & (rr < b))
                                               for a, b in bins},
            "pd_at_rate_m_s": {f"{v:g}": float(np.interp(v, grid, pd_grid)) for v in (0.5, 0.75, 1.0)
                               if grid[0] <= v <= grid[-1]},
            "pfa_per_epoch": pfa,
            "assumes": "knows the channel, the onset and the receiver's state; the channel's white noise "
                       "(sigma_pr_m) and Gauss-Markov error (gm_sigma_m, gm_tau_s) as in the world; a most "
                       "powerful test at every epoch, two-sided; code-only ramp"}


def _pfa_only(n_fa, n):
    lo, hi = scipy.stats.binomtest(n_fa, n).proportion_ci(0.95, method="exact") if n else (math.nan, math.nan)
    return {"value": n_fa / n if n else math.nan, "ci95": [lo, hi], "count": int(n_fa), "of": int(n)}
