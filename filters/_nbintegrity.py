"""Compiled kernel of the integrity monitor's epoch (filters/integrity.py, numpy reference there).

Per trial: innovation, diag(H P- H'), beta, the jump test, the window sums (running: + the new
sample - the one leaving the ring), both window tests, the channel logic (jump runs,
exclusion, readmission), the row mask, Huber weights, the R used by the update and the
innovation-based R estimate.

Layout as in filters/_nbkernels.py: ``_block`` processes trials [lo, hi), LANES at a time, with
its scratch allocated once per block; the drivers spread blocks over the cores (``*_par``) or
run one block (``*_ser``). Every output is allocated by the caller and passed in. Everything a
lane group needs is in that one function: a call per lane group would pay an atomic reference
count on each of its ~45 arrays, shared by the threads (measured: a large part of the cost on
two cores). With ``fuse`` the block then runs the EKF's sequential Joseph update on the lanes
it has loaded (the arithmetic of _nbkernels._joseph_block), taking the monitor's innovations,
mask and R as they are; without, the inert rows of H are zeroed in H and z, h are written out
for a guarded model and any update.
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

from ._nbkernels import LANES, N_BLOCKS, _jit  # noqa: F401 (LANES: the caller reads it here)


@nb.njit(**_jit)
def _block(lo, hi, z, hx, H, P, r_nom, r_est, old_sq, old_b, stale, sum_sq, sum_b, jump_run, excluded, clean_run,
           ch, prm, iprm, beta, jump, drift_stat, bias_stat, drift, inert, used, weight, r_used, y, new_sq, new_b,
           sum_sq2, sum_b2, r_est2, excl2, newly, readmit, jr2, cr2, z_f, hx_g, fuse, x, xo, Po, nis, lanes):
    """The monitor (and with ``fuse`` the EKF's sequential Joseph update) on trials [lo, hi), LANES
    trials at a time in the layout of _nbkernels._joseph_block (P[i, j, lane]): the lanes' P- and
    H are loaded once, diag(H P- H') is computed on them (vectorised over the trials), the
    monitor runs on the lane group, and the update takes its innovations, mask and R on the same
    lanes. The update arithmetic is _joseph_block's (without the prediction), statement for
    statement, so the result equals ekf_update on the guarded model (tested); H is then not
    modified. Without ``fuse``: the inert rows of H are zeroed in H, z_f and hx_g written.

    prm: (J, thr_ms, thr_b, huber_c, lam); iprm: (count, W, use_bias, persist, readmit_after,
    use_huber, adapt_r, isolate, has_stale, write_zh). r_nom has 1 or N rows (shared or per
    trial). Returns the number of readmissions."""
    n = H.shape[2]
    m = z.shape[1]
    C = excluded.shape[1]
    B = lanes
    J, thr_ms, thr_b, huber_c, lam = prm[0], prm[1], prm[2], prm[3], prm[4]
    count, W, use_bias, persist, readmit_after = iprm[0], iprm[1], iprm[2] != 0, iprm[3], iprm[4]
    use_huber, adapt_r, isolate, has_stale, write_zh = iprm[5] != 0, iprm[6] != 0, iprm[7] != 0, iprm[8] != 0, \
        iprm[9] != 0
    J2 = J * J
    shared_r = r_nom.shape[0] == 1
    glob = not fuse  # the row mask and R: batched outputs for a guarded model, else lane-group scratch
    zero_h = glob
    Pl = np.empty((n, n, B))
    Hl = np.empty((m, n, B))
    yl = np.empty((m, B))
    rl = np.empty((m, B))
    hl = np.empty((m, B))
    gl = np.empty(B)
    dx = np.empty((n, B))
    b = np.empty((n, B))
    k = np.empty((n, B))
    nu = np.empty(B)
    sv = np.empty(B)
    acc = np.empty(B)
    idx = np.empty(n, np.int64)
    hq = np.empty((B, m))
    nu_t, rf, q2, qb = np.empty((B, m)), np.empty((B, m)), np.empty((B, m)), np.empty((B, m))
    r_q, inert_q = np.empty((B, m)), np.empty((B, m), np.bool_)
    inert_m = inert if glob else inert_q
    r_m = r_used if glob else r_q
    miss, jmp, drf = np.empty((B, m), np.bool_), np.empty((B, m), np.bool_), np.empty((B, m), np.bool_)
    jump_ch, drift_ch = np.empty((B, C), np.bool_), np.empty((B, C), np.bool_)
    tot = 0
    for t0 in range(lo, hi, B):
        nl = min(B, hi - t0)
        # load, transposed (upper triangle of P); idle lanes get a harmless problem (P = I, H = 0)
        for q in range(B):
            if q < nl:
                t = t0 + q
                for i in range(n):
                    for j in range(i, n):
                        Pl[i, j, q] = P[t, i, j]
                for a in range(m):
                    for i in range(n):
                        Hl[a, i, q] = H[t, a, i]
            else:
                for i in range(n):
                    for j in range(i, n):
                        Pl[i, j, q] = 1.0 if i == j else 0.0
                for a in range(m):
                    for i in range(n):
                        Hl[a, i, q] = 0.0
        # diag(H P- H') per row, across the lanes: sum_i h_i (P_ii h_i + 2 sum_{l > i} P_il h_l)
        for a in range(m):
            for q in range(B):
                hl[a, q] = 0.0
            for i in range(n):
                for q in range(B):
                    gl[q] = Pl[i, i, q] * Hl[a, i, q]
                for l in range(i + 1, n):
                    for q in range(B):
                        gl[q] += 2.0 * Pl[i, l, q] * Hl[a, l, q]
                for q in range(B):
                    hl[a, q] += Hl[a, i, q] * gl[q]
        for q in range(nl):
            for a in range(m):
                hq[q, a] = hl[a, q]
        # the monitor, in passes over the lane group (each pass touches a few batched arrays: one pass
        # over all ~25 at once, trial by trial, defeats the hardware prefetcher, measured 2.4x slower)
        # innovations (a NaN measurement is missing: 0 in its place) and the R in their variance: the
        # nominal one, or the adaptive estimate when larger
        for q in range(nl):
            t = t0 + q
            rt = 0 if shared_r else t
            for j in range(m):
                zj = z[t, j]
                mj = not math.isfinite(zj)
                if mj:
                    zj = 0.0
                miss[q, j] = mj
                nu_t[q, j] = zj - hx[t, j]
                if write_zh:
                    z_f[t, j] = zj
                r = r_nom[rt, j]
                if adapt_r:
                    re = r_est[t, j]
                    if math.isfinite(re) and re > r:
                        r = re
                rf[q, j] = r
        # beta, the jump test and the (winsorised) window samples
        for q in range(nl):
            t = t0 + q
            for j in range(m):
                mj = miss[q, j]
                bj = 0.0 if mj else nu_t[q, j] / math.sqrt(hq[q, j] + rf[q, j])
                beta[t, j] = bj
                jp = (abs(bj) >= J) and not mj
                jmp[q, j] = jp
                jump[t, j] = jp
                v2 = 1.0 if mj else min(bj * bj, J2)
                vb = 0.0 if mj else min(max(bj, -J), J)
                q2[q, j] = v2
                qb[q, j] = vb
                new_sq[t, j] = v2
                new_b[t, j] = vb
        # the window sums: the new sample in, the oldest out (a stale slot leaves as the healthy value)
        for q in range(nl):
            t = t0 + q
            for j in range(m):
                o2 = old_sq[t, j]
                ob = old_b[t, j]
                if has_stale and stale[t, j] > 0:
                    o2, ob = 1.0, 0.0
                sum_sq2[t, j] = sum_sq[t, j] + q2[q, j] - o2
                sum_b2[t, j] = sum_b[t, j] + qb[q, j] - ob
        # both window tests
        for q in range(nl):
            t = t0 + q
            for j in range(m):
                ss = sum_sq2[t, j]
                sb = sum_b2[t, j]
                ds = ss / W if count == W else (ss - (W - count)) / count
                bs = sb * sb / count
                drift_stat[t, j] = ds
                bias_stat[t, j] = bs
                dr = ds > thr_ms or (use_bias and bs > thr_b)
                drf[q, j] = dr
                drift[t, j] = dr
        # the channels: jump runs, exclusion, readmission
        for q in range(nl):
            t = t0 + q
            for c in range(C):
                jump_ch[q, c] = False
                drift_ch[q, c] = False
            for j in range(m):
                c = ch[j]
                if jmp[q, j]:
                    jump_ch[q, c] = True
                if drf[q, j]:
                    drift_ch[q, c] = True
            for c in range(C):
                jc = jump_ch[q, c]
                dc = drift_ch[q, c]
                jr = jump_run[t, c] + 1 if jc else 0
                jr2[t, c] = jr
                fault = dc or jr >= persist
                ex = excluded[t, c]
                clean = not (jc or (dc and not ex))  # out: the window tests do not apply
                cr2[t, c] = clean_run[t, c] + 1 if clean else 0
                if isolate:
                    rd = ex and cr2[t, c] >= readmit_after
                    readmit[t, c] = rd
                    tot += rd
                    excl2[t, c] = (ex or fault) and not rd
                    newly[t, c] = fault and not ex
                else:
                    readmit[t, c] = False
                    excl2[t, c] = False
                    newly[t, c] = fault
        # the row mask, Huber weights, the R and the innovations the update uses
        for q in range(nl):
            t = t0 + q
            for j in range(m):
                it = miss[q, j]
                if isolate:
                    it = it or jmp[q, j] or excl2[t, ch[j]]
                inert_m[t if glob else q, j] = it
                used[t, j] = not it
                w = 0.0 if it else 1.0
                r = rf[q, j]
                if use_huber and not it:
                    ab = abs(beta[t, j])
                    if ab > huber_c:
                        w = huber_c / max(ab, 1e-300)
                        r = r * (1.0 / w)
                weight[t, j] = w
                r_m[t if glob else q, j] = r
                y[t, j] = 0.0 if it else nu_t[q, j]
                # the innovation-based R estimate (admitted rows)
                if adapt_r:
                    re = r_est[t, j]
                    if not it:
                        sample = nu_t[q, j] * nu_t[q, j] - hq[q, j]
                        re = (1.0 - lam) * re + lam * sample if math.isfinite(re) else sample
                    r_est2[t, j] = re
        if write_zh or zero_h:
            for q in range(nl):
                t = t0 + q
                for j in range(m):
                    it = inert_m[t if glob else q, j]
                    if write_zh:
                        hx_g[t, j] = z_f[t, j] if it else hx[t, j]
                    if zero_h and it:
                        for a in range(n):
                            H[t, j, a] = 0.0
        if not fuse:
            continue
        for q in range(nl):
            t = t0 + q
            for a in range(m):
                yl[a, q] = y[t, a]
                rl[a, q] = r_q[q, a]
                if inert_q[q, a]:
                    for i in range(n):
                        Hl[a, i, q] = 0.0
        for q in range(nl, B):
            for a in range(m):
                yl[a, q] = 0.0
                rl[a, q] = 1.0
        # the sequential Joseph update (_nbkernels._joseph_block)
        for i in range(n):
            for q in range(B):
                dx[i, q] = 0.0
        for q in range(B):
            acc[q] = 0.0
        for a in range(m):
            nz = 0
            for i in range(n):
                any_ = False
                for q in range(B):
                    if Hl[a, i, q] != 0.0:
                        any_ = True
                if any_:
                    idx[nz] = i
                    nz += 1
            for q in range(B):
                nu[q] = yl[a, q]
            for c in range(nz):
                i = idx[c]
                for q in range(B):
                    nu[q] -= Hl[a, i, q] * dx[i, q]
            for i in range(n):
                for q in range(B):
                    b[i, q] = 0.0
            for c in range(nz):
                l = idx[c]
                for i in range(l + 1):
                    for q in range(B):
                        b[i, q] += Pl[i, l, q] * Hl[a, l, q]
                for i in range(l + 1, n):
                    for q in range(B):
                        b[i, q] += Pl[l, i, q] * Hl[a, l, q]
            for q in range(B):
                sv[q] = rl[a, q]
            for c in range(nz):
                i = idx[c]
                for q in range(B):
                    sv[q] += Hl[a, i, q] * b[i, q]
            for i in range(n):
                for q in range(B):
                    k[i, q] = b[i, q] / sv[q]
                    dx[i, q] += k[i, q] * nu[q]
            for q in range(B):
                acc[q] += nu[q] * nu[q] / sv[q]
            for i in range(n):
                for l in range(i, n):
                    for q in range(B):
                        Pl[i, l, q] += (sv[q] * k[i, q] - b[i, q]) * k[l, q] - k[i, q] * b[l, q]
        for q in range(nl):
            t = t0 + q
            nis[t] = acc[q]
            for i in range(n):
                xo[t, i] = x[t, i] + dx[i, q]
                for l in range(i, n):
                    Po[t, i, l] = Pl[i, l, q]
                    Po[t, l, i] = Pl[i, l, q]
    return tot


@nb.njit(parallel=True, **_jit)
def epoch_par(z, hx, H, P, r_nom, r_est, old_sq, old_b, stale, sum_sq, sum_b, jump_run, excluded, clean_run, ch,
              prm, iprm, beta, jump, drift_stat, bias_stat, drift, inert, used, weight, r_used, y, new_sq, new_b,
              sum_sq2, sum_b2, r_est2, excl2, newly, readmit, jr2, cr2, z_f, hx_g, fuse, x, xo, Po, nis, lanes):
    N = z.shape[0]
    nb_ = min(N, N_BLOCKS)
    tot = 0
    for blk in nb.prange(nb_):
        lo, hi = blk * N // nb_, (blk + 1) * N // nb_
        tot += _block(lo, hi, z, hx, H, P, r_nom, r_est, old_sq, old_b, stale, sum_sq, sum_b, jump_run,
                                excluded, clean_run, ch, prm, iprm, beta, jump, drift_stat, bias_stat, drift, inert,
                                used, weight, r_used, y, new_sq, new_b, sum_sq2, sum_b2, r_est2, excl2, newly,
                                readmit, jr2, cr2, z_f, hx_g, fuse, x, xo, Po, nis, lanes)
    return tot


@nb.njit(**_jit)
def epoch_ser(z, hx, H, P, r_nom, r_est, old_sq, old_b, stale, sum_sq, sum_b, jump_run, excluded, clean_run, ch,
              prm, iprm, beta, jump, drift_stat, bias_stat, drift, inert, used, weight, r_used, y, new_sq, new_b,
              sum_sq2, sum_b2, r_est2, excl2, newly, readmit, jr2, cr2, z_f, hx_g, fuse, x, xo, Po, nis, lanes):
    N = z.shape[0]
    # np.int64(0): a literal 0 would compile _block a second time, for the type Literal[int](0)
    return _block(np.int64(0), N, z, hx, H, P, r_nom, r_est, old_sq, old_b, stale, sum_sq, sum_b, jump_run,
                  excluded, clean_run, ch, prm, iprm, beta, jump, drift_stat, bias_stat, drift, inert, used, weight,
                  r_used, y, new_sq, new_b, sum_sq2, sum_b2, r_est2, excl2, newly, readmit, jr2, cr2, z_f,
                  hx_g, fuse, x, xo, Po, nis, lanes)
