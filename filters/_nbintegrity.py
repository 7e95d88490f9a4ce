"""Compiled kernel of the integrity monitor's epoch (filters/integrity.py, numpy reference there).

Per trial: innovation, diag(H P- H'), beta, the jump test, the window sums (running: + the new
sample - the one leaving the ring: one ring of winsorised beta, NaN for a missing epoch), both
window tests, the channel logic (jump runs, exclusion, readmission), the row mask, the Huber
weight in R, the R used by the update and the innovation-based R estimate. The Report's jump and
drift flags, window statistics and Huber weights are not written here: the Report derives them
from beta and the window sums when read (the flags by the very comparisons made here).

Layout as in filters/_nbkernels.py: ``_block`` processes trials [lo, hi), LANES at a time, with
its scratch allocated once per block; the drivers spread blocks over the cores (``*_par``) or
run one block (``*_ser``). Every output is allocated by the caller and passed in. Everything a
lane group needs is in that one function: a call per lane group would pay an atomic reference
count on each of its ~40 arrays, shared by the threads (measured: a large part of the cost on
two cores). The monitor works on [row, lane] scratch (the channel logic on [channel, lane]),
looping over the lanes; the loops are written select by select (no min/max, isfinite or
short-circuit tests), so that LLVM vectorises them (checked with its loop-vectorize remarks).
The monitor's own state (window sums, R estimate, channel counters and flags) is kept lane-tiled
by filters.integrity.MonitorState and copied in and out as contiguous blocks; the other batched
arrays are touched by one transposing load and one store per lane group (a trial-major monitor
reading them in place was slower: LLVM gives up vectorising a loop over a trial's 16 rows that
touches ~20 arrays, for want of alias checks). With ``fuse`` the block then
runs the EKF's sequential Joseph update on the lanes it has loaded (_nbkernels._joseph_lanes, the
core of _nbkernels._joseph_block, inlined), taking the monitor's innovations, mask and R as they are; without,
the inert rows of H are zeroed in H and z, h are written out for a guarded model and any update.
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

from ._nbkernels import LANES, N_BLOCKS, _jit  # noqa: F401 (LANES: the caller reads it here)
from ._nbkernels import _joseph_lanes, _joseph_scratch, _lane_columns, _store_lanes


@nb.njit(**_jit)
def _block(g0, g1, N, z, hx, H, P, r_nom, r_est, old, stale, sum_sq, sum_b, jump_run, excluded, clean_run,
           ch, prm, iprm, beta, inert, used, r_used, y, ring_new, sum_sq2, sum_b2, r_est2,
           newly, jr2, cr2, excl2_t, z_f, hx_g, fuse, x, xo, Po, nis, lanes):
    """The monitor (and with ``fuse`` the EKF's sequential Joseph update) on lane groups [g0, g1)
    of the N trials (trials g B .. g B + B - 1, B = lanes), in the layout of
    _nbkernels._joseph_block: every quantity of the lane group is held as [row, lane] (P as
    [i, j, lane]) in scratch local to this function, so that each step of the monitor is a loop
    over the lanes that LLVM vectorises. diag(H P- H') runs over the columns of each row
    that are nonzero in some lane (a pseudorange row has 4 of 8). The update is _joseph_block's
    own core (_nbkernels._joseph_lanes, without the prediction), so the result equals
    ekf_update on the guarded model (tested); H is then not modified. Without ``fuse``: the inert
    rows of H are zeroed in H, z_f, hx_g, inert and r_used written.

    prm: (J, thr_ss, thr_bs, huber_c, lam) -- the window tests' tolerances on the sums themselves (the
    mean of beta^2 above its tolerance: sum_sq > thr_ss; the bias test: sum_b^2 > thr_bs; the caller
    computes both, so that the Report derives the same flags from the same sums bit for bit);
    iprm: (persist, readmit_after, use_huber, adapt_r, isolate, has_stale, min_channels, step: the
    epoch's number, a row's leaving slot is stale while step < stale) -- the window length, the
    epochs seen and the bias test are in thr_ss and thr_bs. r_nom has 1 or N rows (shared or per trial). Returns the number of
    readmissions.

    The monitor's own per-row and per-channel state (r_est, sum_sq, sum_b; jump_run, excluded,
    clean_run; and the new ones r_est2, sum_sq2, sum_b2, jr2, cr2, excl2_t) is lane-tiled,
    (groups, rows or channels, lanes) -- filters.integrity.MonitorState keeps it so -- and is read
    and written as contiguous blocks, not transposed. The Report's excluded and readmitted
    channels are not written: they are excl2_t and, where the old one was set, not excl2_t."""
    n = H.shape[2]
    m = z.shape[1]
    C = excluded.shape[1]
    B = lanes
    J, thr_ss, thr_bs, huber_c, lam = prm[0], prm[1], prm[2], prm[3], prm[4]
    persist, readmit_after = iprm[0], iprm[1]
    use_huber, adapt_r, isolate, has_stale = iprm[2] != 0, iprm[3] != 0, iprm[4] != 0, iprm[5] != 0
    min_ch, step = iprm[6], iprm[7]
    glob = not fuse  # a guarded model follows: z_f, hx_g, the row mask and R go out, H rows are zeroed
    shared_r = r_nom.shape[0] == 1
    Pl = np.empty((n, n, B))
    Hl = np.empty((m, n, B))
    hl = np.empty((m, B))
    gl = np.empty(B)
    nzr = np.empty((m, n), np.int64)
    nzc = np.empty(m, np.int64)
    zl, hxl, nul, rl, bl, yl = (np.empty((m, B)), np.empty((m, B)), np.empty((m, B)), np.empty((m, B)),
                                np.empty((m, B)), np.empty((m, B)))
    sbl, ssl, sbs, rel = np.empty((m, B)), np.empty((m, B)), np.empty((m, B)), np.empty((m, B))
    rnl = np.empty((m, B))
    missl, jmpl, drfl, inl = (np.empty((m, B), np.bool_), np.empty((m, B), np.bool_), np.empty((m, B), np.bool_),
                              np.empty((m, B), np.bool_))
    jcl, dcl, exl, pcl = (np.empty((C, B), np.bool_), np.empty((C, B), np.bool_), np.empty((C, B), np.bool_),
                          np.empty((C, B), np.bool_))
    exo, fl, rdl = np.empty((C, B), np.bool_), np.empty((C, B), np.bool_), np.empty((C, B), np.bool_)
    jrl, crl = np.empty((C, B), np.int64), np.empty((C, B), np.int64)
    n_in = np.empty(B, np.int64)
    n_full = np.empty(B, np.int64)
    model_ = np.empty(B, np.int64)  # per lane: the isolation mode of the epoch
    dx, b, k, nu, sv, acc = _joseph_scratch(n, B)
    tot = 0
    for g in range(g0, g1):
        t0 = g * B
        nl = min(B, N - t0)
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
        # the nominal R, [row, lane] (shared by every trial: a fill, else transposed; filling a shared R
        # once before the first group was measured 1.2 ms slower per 10k trials, single thread)
        if shared_r:
            for j in range(m):
                for q in range(nl):
                    rnl[j, q] = r_nom[0, j]
        else:
            for q in range(nl):
                for j in range(m):
                    rnl[j, q] = r_nom[t0 + q, j]
        # the per-row vectors of the lane group, transposed to [row, lane]
        for j in range(m):  # the monitor's state: lane-tiled, a contiguous block each
            for q in range(B):
                ssl[j, q] = sum_sq[g, j, q]
            for q in range(B):
                sbs[j, q] = sum_b[g, j, q]
            if adapt_r:
                for q in range(B):
                    rel[j, q] = r_est[g, j, q]
            else:
                for q in range(B):
                    rel[j, q] = -math.inf
        for c in range(C):
            for q in range(B):
                jrl[c, q] = jump_run[g, c, q]
            for q in range(B):
                crl[c, q] = clean_run[g, c, q]
            for q in range(B):
                exo[c, q] = excluded[g, c, q]
        for q in range(nl):
            t = t0 + q
            for j in range(m):
                zl[j, q] = z[t, j]
                hxl[j, q] = hx[t, j]
                sbl[j, q] = old[t, j]
            if has_stale:  # a stale slot leaves the window as the healthy value it stands for (NaN: missing)
                for j in range(m):
                    if stale[t, j] > step:
                        sbl[j, q] = math.nan
        _lane_columns(Hl, nzr, nzc)  # the columns of each row that are nonzero in some lane
        # per row, across the lanes: diag(H P- H') = sum_i h_i (P_ii h_i + 2 sum_{l > i} P_il h_l), the
        # innovation (a NaN measurement is missing: 0 in its place), the R in its variance (the nominal
        # one or the adaptive estimate when larger), beta, the jump test, the winsorised window samples,
        # the running window sums (the new sample in, the oldest out) and both window tests
        for a in range(m):
            if nzc[a] == 4:  # (pseudorange and Doppler rows: position or velocity, and clock) one pass
                i0, i1, i2, i3 = nzr[a, 0], nzr[a, 1], nzr[a, 2], nzr[a, 3]
                for q in range(nl):
                    h0, h1, h2, h3 = Hl[a, i0, q], Hl[a, i1, q], Hl[a, i2, q], Hl[a, i3, q]
                    hl[a, q] = (h0 * (Pl[i0, i0, q] * h0 + 2.0 * (Pl[i0, i1, q] * h1 + Pl[i0, i2, q] * h2
                                                                   + Pl[i0, i3, q] * h3))
                                + h1 * (Pl[i1, i1, q] * h1 + 2.0 * (Pl[i1, i2, q] * h2 + Pl[i1, i3, q] * h3))
                                + h2 * (Pl[i2, i2, q] * h2 + 2.0 * Pl[i2, i3, q] * h3) + h3 * (Pl[i3, i3, q] * h3))
            else:
                for q in range(nl):
                    hl[a, q] = 0.0
                for c in range(nzc[a]):
                    i = nzr[a, c]
                    for q in range(nl):
                        gl[q] = Pl[i, i, q] * Hl[a, i, q]
                    for d in range(c + 1, nzc[a]):
                        l = nzr[a, d]
                        for q in range(nl):
                            gl[q] += 2.0 * Pl[i, l, q] * Hl[a, l, q]
                    for q in range(nl):
                        hl[a, q] += Hl[a, i, q] * gl[q]
            # (written select by select, without min/max, isfinite or branches: LLVM vectorises it)
            for q in range(nl):
                zj = zl[a, q]
                fin = abs(zj) < math.inf
                zj = zj if fin else 0.0
                v = zj - hxl[a, q]
                r = rnl[a, q]
                re = rel[a, q]  # (-inf without the adaptive R)
                r = re if (re > r) & (re < math.inf) else r
                bj = v / math.sqrt(hl[a, q] + r)
                bj = bj if fin else 0.0
                jp = (abs(bj) >= J) & fin
                cb = bj if bj > -J else -J  # noqa: FURB136 (min/max would keep LLVM from vectorising)
                cb = cb if cb < J else J  # noqa: FURB136
                v2 = cb * cb if fin else 1.0
                vb = cb if fin else 0.0
                o = sbl[a, q]  # the sample leaving the window (NaN: a missing epoch, 1 and 0)
                om = o != o  # noqa: PLR0124 (NaN)
                ss = ssl[a, q] + v2 - (1.0 if om else o * o)
                sb = sbs[a, q] + vb - (0.0 if om else o)
                if glob:  # (z without NaN: only a guarded model needs it)
                    zl[a, q] = zj
                nul[a, q] = v
                rl[a, q] = r
                bl[a, q] = bj
                missl[a, q] = not fin
                jmpl[a, q] = jp
                sbl[a, q] = cb if fin else math.nan
                ssl[a, q] = ss
                sbs[a, q] = sb
                drfl[a, q] = (ss > thr_ss) | (sb * sb > thr_bs)
        # the channels: jump runs, exclusion, readmission; a member isolates only while at least
        # min_channels of its present channels stay in (mode 2: rows and channels left out; 1: only
        # the excluded channels, the jumped rows used; 0: detect only, nothing excluded)
        for c in range(C):
            for q in range(nl):
                jcl[c, q] = False
                dcl[c, q] = False
                pcl[c, q] = False
        for a in range(m):
            c = ch[a]
            for q in range(nl):
                jcl[c, q] = jcl[c, q] | jmpl[a, q]
                dcl[c, q] = dcl[c, q] | drfl[a, q]
                pcl[c, q] = pcl[c, q] | (not missl[a, q])
        # per channel and lane, branch-free (vectorised across the lanes)
        for q in range(B):
            n_in[q] = 0
            n_full[q] = 0
        for c in range(C):
            for q in range(nl):
                jc = jcl[c, q]
                dc = dcl[c, q]
                ex = exo[c, q]
                jr = jrl[c, q] + 1 if jc else 0
                fault = dc | (jr >= persist)
                clean = not (jc | (dc & (not ex)))  # out: the window tests do not apply
                cr = crl[c, q] + 1 if clean else 0
                rd = isolate & ex & (cr >= readmit_after)
                e2 = isolate & (ex | fault) & (not rd)
                jrl[c, q] = jr
                crl[c, q] = cr
                fl[c, q] = fault
                rdl[c, q] = rd
                exl[c, q] = e2
                keep = pcl[c, q] & (not e2)
                n_in[q] += keep
                n_full[q] += keep & (not jc)
        for q in range(nl):
            md = 2 if n_full[q] >= min_ch else (1 if n_in[q] >= min_ch else 0)
            model_[q] = md if isolate else 0
        for c in range(C):
            for q in range(nl):
                det = model_[q] == 0  # detect only: every fault reported, a channel that was out comes back
                ex = exo[c, q]
                rd = (ex & isolate) if det else rdl[c, q]
                rdl[c, q] = rd
                exl[c, q] = False if det else exl[c, q]
                fl[c, q] = fl[c, q] if det else (fl[c, q] & (not ex))
                tot += rd
        # the row mask, the Huber weight in R (R / w), the innovations the update uses and the
        # innovation-based R estimate (admitted rows)
        for a in range(m):
            c = ch[a]
            for q in range(nl):
                it = missl[a, q] | (exl[c, q] | (jmpl[a, q] & (model_[q] == 2)))
                inl[a, q] = it
                if use_huber:
                    ab = abs(bl[a, q])
                    ab1 = ab if ab > 1e-300 else 1e-300  # noqa: FURB136
                    rh = rl[a, q] * (1.0 / (huber_c / ab1))
                    rl[a, q] = rh if (ab > huber_c) & (not it) else rl[a, q]
                yl[a, q] = 0.0 if it else nul[a, q]
                if adapt_r:
                    re = rel[a, q]
                    v = nul[a, q]
                    smp = v * v - hl[a, q]
                    rn = rnl[a, q]
                    wj = rn / (hl[a, q] + rn)  # the sample's precision against one at a known prior
                    lj = lam * wj * wj
                    upd = (1.0 - lj) * (re if abs(re) < math.inf else rn) + lj * smp
                    rel[a, q] = re if it else upd
        # the lane group's outputs, transposed back
        for c in range(C):  # (idle lanes keep what they hold)
            for q in range(nl, B):
                exl[c, q] = exo[c, q]
        for j in range(m):
            for q in range(B):
                sum_sq2[g, j, q] = ssl[j, q]
            for q in range(B):
                sum_b2[g, j, q] = sbs[j, q]
            if adapt_r:
                for q in range(B):
                    r_est2[g, j, q] = rel[j, q]
        for c in range(C):
            for q in range(B):
                jr2[g, c, q] = jrl[c, q]
            for q in range(B):
                cr2[g, c, q] = crl[c, q]
            for q in range(B):
                excl2_t[g, c, q] = exl[c, q]
        for q in range(nl):
            t = t0 + q
            for j in range(m):
                beta[t, j] = bl[j, q]
                used[t, j] = not inl[j, q]
                y[t, j] = yl[j, q]
                ring_new[t, j] = sbl[j, q]
            for c in range(C):
                newly[t, c] = fl[c, q]
            if glob:
                for j in range(m):
                    it = inl[j, q]
                    inert[t, j] = it
                    r_used[t, j] = rl[j, q]
                    z_f[t, j] = zl[j, q]
                    hx_g[t, j] = zl[j, q] if it else hxl[j, q]
                    if it:
                        for a in range(n):
                            H[t, j, a] = 0.0
        if glob:
            continue
        for a in range(m):
            for q in range(nl):
                if inl[a, q]:
                    for i in range(n):
                        Hl[a, i, q] = 0.0
            for q in range(nl, B):
                yl[a, q] = 0.0
                rl[a, q] = 1.0
        # the EKF's sequential Joseph update (the same core as _nbkernels._joseph_block), on the
        # columns of each row nonzero in some lane before the mask (a masked row's zeros add exact zeros)
        _joseph_lanes(Pl, Hl, yl, rl, nzr, nzc, dx, b, k, nu, sv, acc)
        _store_lanes(x, dx, Pl, acc, xo, Po, nis, t0, nl)
    return tot


@nb.njit(parallel=True, **_jit)
def epoch_par(z, hx, H, P, r_nom, r_est, old, stale, sum_sq, sum_b, jump_run, excluded, clean_run, ch,
              prm, iprm, beta, inert, used, r_used, y, ring_new, sum_sq2, sum_b2, r_est2,
              newly, jr2, cr2, excl2_t, z_f, hx_g, fuse, x, xo, Po, nis, lanes):
    N = z.shape[0]
    G = sum_sq.shape[0]  # lane groups (the tiles of the monitor's state)
    nb_ = min(G, N_BLOCKS)
    tot = 0
    for blk in nb.prange(nb_):
        g0, g1 = blk * G // nb_, (blk + 1) * G // nb_
        tot += _block(g0, g1, N, z, hx, H, P, r_nom, r_est, old, stale, sum_sq, sum_b, jump_run, excluded,
                      clean_run, ch, prm, iprm, beta, inert, used, r_used, y, ring_new, sum_sq2,
                      sum_b2, r_est2,  newly, jr2, cr2, excl2_t, z_f, hx_g, fuse, x, xo, Po, nis,
                      lanes)
    return tot


@nb.njit(**_jit)
def epoch_ser(z, hx, H, P, r_nom, r_est, old, stale, sum_sq, sum_b, jump_run, excluded, clean_run, ch,
              prm, iprm, beta, inert, used, r_used, y, ring_new, sum_sq2, sum_b2, r_est2,
              newly, jr2, cr2, excl2_t, z_f, hx_g, fuse, x, xo, Po, nis, lanes):
    N = z.shape[0]
    # np.int64(0): a literal 0 would compile _block a second time, for the type Literal[int](0)
    return _block(np.int64(0), sum_sq.shape[0], N, z, hx, H, P, r_nom, r_est, old, stale, sum_sq, sum_b, jump_run,
                  excluded, clean_run, ch, prm, iprm, beta, inert, used, r_used, y, ring_new,
                  sum_sq2, sum_b2, r_est2,  newly, jr2, cr2, excl2_t, z_f, hx_g, fuse, x, xo, Po, nis,
                  lanes)
