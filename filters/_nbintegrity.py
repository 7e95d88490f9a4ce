"""Compiled kernel of the integrity monitor's epoch (filters/integrity.py, numpy reference there).

One pass per trial over the rows: innovation, diag(H P H'), beta, the jump test, the window
sums (running: + the new sample - the one leaving the ring), both window tests, the channel
logic (jump runs, exclusion, readmission), the row mask, Huber weights, the R used by the
update, the innovation-based R estimate, and H with the inert rows zeroed. Trials in parallel.
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np


@nb.njit(parallel=True, cache=True, fastmath=False)
def monitor_epoch(z, hx, H, P, r_nom, r_est, old_sq, old_b, sum_sq, sum_b, jump_run, excluded, clean_run, ch,
                  J, count, W, thr_ms, thr_b, use_bias, persist, readmit_after, huber_c, use_huber, adapt_r, lam,
                  isolate, inplace):
    N, m, n = H.shape
    C = excluded.shape[1]
    beta = np.empty((N, m))
    jump = np.empty((N, m), dtype=np.bool_)
    drift_stat = np.empty((N, m))
    bias_stat = np.empty((N, m))
    drift = np.empty((N, m), dtype=np.bool_)
    inert = np.empty((N, m), dtype=np.bool_)
    weight = np.empty((N, m))
    r_used = np.empty((N, m))
    new_sq = np.empty((N, m))
    new_b = np.empty((N, m))
    sum_sq2 = np.empty((N, m))
    sum_b2 = np.empty((N, m))
    hx_out = np.empty((N, m))
    H_out = H if inplace else np.empty((N, m, n))
    r_est2 = np.empty((N, m))
    excl2 = np.empty((N, C), dtype=np.bool_)
    newly = np.empty((N, C), dtype=np.bool_)
    readmit = np.empty((N, C), dtype=np.bool_)
    jr2 = np.empty((N, C), dtype=np.int64)
    cr2 = np.empty((N, C), dtype=np.int64)
    z_f = np.empty((N, m))
    J2 = J * J
    # scratch per trial, allocated once (an allocation per trial costs as much as the arithmetic)
    nu_a = np.empty((N, m))
    hph_a = np.empty((N, m))
    miss_a = np.empty((N, m), dtype=np.bool_)
    jump_ch_a = np.zeros((N, C), dtype=np.bool_)
    drift_ch_a = np.zeros((N, C), dtype=np.bool_)
    for t in nb.prange(N):
        nu = nu_a[t]
        hph = hph_a[t]
        miss = miss_a[t]
        jump_ch = jump_ch_a[t]
        drift_ch = drift_ch_a[t]
        for j in range(m):
            zj = z[t, j]
            mj = not math.isfinite(zj)
            miss[j] = mj
            z_f[t, j] = 0.0 if mj else zj
            s = 0.0
            for a in range(n):
                ha = H[t, j, a]
                if not inplace:
                    H_out[t, j, a] = ha
                if ha != 0.0:
                    pa = 0.5 * P[t, a, a] * ha
                    for b in range(a + 1, n):
                        pa += P[t, a, b] * H[t, j, b]
                    s += ha * pa
            s = 2.0 * s
            hph[j] = s
            nu[j] = z_f[t, j] - hx[t, j]
            rn = r_nom[t, j]
            re = r_est[t, j]
            rf = rn
            if adapt_r and math.isfinite(re) and re > rn:
                rf = re
            r_used[t, j] = rf
            if mj:
                bj = 0.0
            else:
                bj = nu[j] / math.sqrt(s + rf)
            beta[t, j] = bj
            jp = (abs(bj) >= J) and not mj
            jump[t, j] = jp
            # window sums: the new (winsorised) sample in, the oldest out
            if mj:
                q, qb = 1.0, 0.0
            else:
                q = min(bj * bj, J2)
                qb = min(max(bj, -J), J)
            new_sq[t, j] = q
            new_b[t, j] = qb
            ss = sum_sq[t, j] + q - old_sq[t, j]
            sb = sum_b[t, j] + qb - old_b[t, j]
            sum_sq2[t, j] = ss
            sum_b2[t, j] = sb
            ds = ss / W if count == W else (ss - (W - count)) / count
            bs = sb * sb / count
            drift_stat[t, j] = ds
            bias_stat[t, j] = bs
            dr = ds > thr_ms or (use_bias and bs > thr_b)
            drift[t, j] = dr
            c = ch[j]
            if jp:
                jump_ch[c] = True
            if dr:
                drift_ch[c] = True
        for c in range(C):
            jr = jump_run[t, c] + 1 if jump_ch[c] else 0
            jr2[t, c] = jr
            fault = drift_ch[c] or jr >= persist
            ex = excluded[t, c]
            clean = not (jump_ch[c] or (drift_ch[c] and not ex))  # out: window tests do not apply
            cr = clean_run[t, c] + 1 if clean else 0
            cr2[t, c] = cr
            newly[t, c] = fault and not ex
            if isolate:
                rd = ex and cr >= readmit_after
                readmit[t, c] = rd
                excl2[t, c] = (ex or fault) and not rd
            else:
                readmit[t, c] = False
                excl2[t, c] = False
                newly[t, c] = fault
        for j in range(m):
            if isolate:
                it = miss[j] or jump[t, j] or excl2[t, ch[j]]
            else:
                it = miss[j]
            inert[t, j] = it
            w = 1.0
            if use_huber:
                ab = abs(beta[t, j])
                if ab > huber_c:
                    w = huber_c / max(ab, 1e-300)
            if it:
                w = 0.0
            weight[t, j] = w
            if use_huber and not it:
                r_used[t, j] = r_used[t, j] * (1.0 / w)
            if it:
                hx_out[t, j] = z_f[t, j]
                for a in range(n):
                    H_out[t, j, a] = 0.0
            else:
                hx_out[t, j] = hx[t, j]
            re = r_est[t, j]
            if adapt_r and not it:
                sample = nu[j] * nu[j] - hph[j]
                if math.isfinite(re):
                    re = (1.0 - lam) * re + lam * sample
                else:
                    re = sample
            r_est2[t, j] = re
    return (z_f, beta, jump, drift_stat, bias_stat, drift, inert, weight, r_used, new_sq, new_b, sum_sq2, sum_b2,
            hx_out, H_out, r_est2, excl2, newly, readmit, jr2, cr2)
