"""References for `skyfuse gnss solve`: the dual-frequency slant ionosphere of the same file,
broadcast Klobuchar, and RTKLIB's L1 single-point solution (rnx2rtkp), when installed.

Dual-frequency reference (GPS L1/L2, metres of L1 group delay):
    I_code  = (P2 - C1) / (gamma - 1) - c TGD            gamma = (f1/f2)^2
    I_phase = (L1 - L2) / (gamma - 1)                     (phases in metres; + ambiguity)
    levelled I = I_phase + mean over the arc of (I_code - I_phase), elevation >= mask.
An arc ends at a loss-of-lock flag (LLI bit 0 on L1 or L2), a missing epoch, or a jump of the
geometry-free phase of more than 0.5 m between epochs. With the broadcast TGD
(P1 - P2 of the satellite, IS-GPS-200 20.3.3.3.3.2): P2 - P1 = (gamma - 1)(I + c TGD) + b_rx.
C1 is taken for P1 (the P1-C1 satellite bias, a few decimetres of code, ignored). The receiver
code bias b_rx / (gamma - 1) is estimated as one constant per file with the zenith values by
least squares, levelled_jk = m_I(el_jk) I_z(k) + b (the seed's thin-shell mapping): I_z per
epoch, b common, solvable because m_I differs across the satellites of an epoch.

Iono-free static fix (iono_free_static_fix): what the file's two frequencies say the position is
once the ionosphere is gone (first order), with the same broadcast orbits and clocks the L1 filter
uses. P_IF = (gamma C1 - P2) / (gamma - 1) + c dt_sv (the broadcast clock refers to the P1/P2
iono-free combination: no TGD), Saastamoinen with a standard atmosphere, one static position and
one clock per epoch by weighted least squares (RTKLIB's code variance a^2 + b^2 / sin^2 el, a = b).
Its error against the reference position is the part of an L1 solution's error that no ionosphere
estimate can remove: broadcast orbit and clock errors projected on the position (nearly constant
over an hour), the satellites' P1-C1 code biases (ignored; times gamma / (gamma - 1) = 2.55 in
this combination), multipath.
"""
from __future__ import annotations

import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np

from sitl.constants import C_M_S

F1_HZ = 1575.42e6
F2_HZ = 1227.60e6
GAMMA = (F1_HZ / F2_HZ) ** 2
ARC_JUMP_M = 0.5


def arcs(valid, lli, gf_m):
    """Arc number per (T, S) sample (-1 where not valid); new arc at LLI, gap or a jump."""
    T, S = valid.shape
    out = np.full((T, S), -1, dtype=int)
    n = 0
    for j in range(S):
        cur = -1
        for k in range(T):
            if not valid[k, j]:
                cur = -1
                continue
            brk = cur < 0 or (lli[k, j] & 1) or abs(gf_m[k, j] - gf_m[k - 1, j]) > ARC_JUMP_M
            if brk:
                cur = n
                n += 1
            out[k, j] = cur
    return out


def dual_frequency_slant(c1_m, p2_m, l1_cyc, l2_cyc, lli, tgd_s, use):
    """Levelled slant L1 iono (T, S) before the receiver bias, and the arc ids."""
    l1 = l1_cyc * C_M_S / F1_HZ
    l2 = l2_cyc * C_M_S / F2_HZ
    i_code = (p2_m - c1_m) / (GAMMA - 1.0) - C_M_S * tgd_s
    i_phase = (l1 - l2) / (GAMMA - 1.0)  # L_i = rho - I_i + amb, I_2 = gamma I_1
    valid = use & np.isfinite(i_code) & np.isfinite(i_phase)
    arc = arcs(valid, lli, np.where(valid, l1 - l2, 0.0))
    lev = np.full(i_code.shape, np.nan)
    for a in np.unique(arc[arc >= 0]):
        m = arc == a
        lev[m] = i_phase[m] + np.mean(i_code[m] - i_phase[m])
    return lev, arc


def zenith_and_bias(slant_m, m_iono):
    """Least squares slant_jk = m_jk I_z(k) + b: (I_z (T,), b, residual RMS)."""
    T, S = slant_m.shape
    kk, jj = np.nonzero(np.isfinite(slant_m))
    if kk.size == 0:  # no dual-frequency data (an L1-only file)
        return np.full(T, np.nan), float("nan"), float("nan")
    A = np.zeros((kk.size, T + 1))
    A[np.arange(kk.size), kk] = m_iono[kk, jj]
    A[:, T] = 1.0
    y = slant_m[kk, jj]
    has = np.zeros(T, dtype=bool)
    has[kk] = True
    cols = np.append(np.flatnonzero(has), T)
    sol, *_ = np.linalg.lstsq(A[:, cols], y, rcond=None)
    iz = np.full(T, np.nan)
    iz[cols[:-1]] = sol[:-1]
    res = y - A[:, cols] @ sol
    return iz, float(sol[-1]), float(np.sqrt(np.mean(res * res)))


IF_SIGMA_M = 0.3  # RTKLIB's a = b = err-ratio 100 x 0.003 m; only the relative weights matter here
IF_ITERATIONS = 4


def iono_free_code_m(ep):
    """(T, S) iono-free code with the broadcast satellite clock (ep.pr_m holds C1 + c (dt_sv - TGD))."""
    return (GAMMA * ep.c1_m - ep.p2_m) / (GAMMA - 1.0) + (ep.pr_m - ep.c1_m) + C_M_S * np.nan_to_num(ep.tgd_s)


def iono_free_static_fix(ep, ref_ecef_m, el_mask_deg: float):
    """One static position (and a clock per epoch) from the iono-free code of the whole file:
    {"pos_ecef_m", "enu_error_m" (against ref), "rms_residual_m", "by_satellite" (mean, std of the
    residual, m), "epochs", "samples"}, or None without second-frequency code."""
    from sitl.geodesy import ecef_to_aer, ecef_to_enu, ecef_to_geodetic
    from sitl.gnss.saastamoinen import saastamoinen_delay_m

    ref = np.asarray(ref_ecef_m, float)
    lat, lon, h = ecef_to_geodetic(ref)
    p_if = iono_free_code_m(ep)
    x = ref.copy()
    for _ in range(IF_ITERATIONS):
        _, el, _ = ecef_to_aer(x, ep.sat_pos_m)
        ok = np.isfinite(p_if) & np.isfinite(el) & (el >= np.radians(el_mask_deg))
        kk, jj = np.nonzero(ok)
        if kk.size <= 3 + np.unique(kk).size:  # no second-frequency code, or too few samples
            return None
        d = ep.sat_pos_m[kk, jj] - x
        rho = np.linalg.norm(d, axis=-1)
        e = el[kk, jj]
        y = p_if[kk, jj] - rho - saastamoinen_delay_m(lat, h, e)
        epochs, col = np.unique(kk, return_inverse=True)
        A = np.zeros((kk.size, 3 + epochs.size))
        A[:, :3] = -d / rho[:, None]
        A[np.arange(kk.size), 3 + col] = 1.0
        w = 1.0 / (IF_SIGMA_M * np.sqrt(1.0 + 1.0 / np.sin(e) ** 2))
        sol, *_ = np.linalg.lstsq(A * w[:, None], y * w, rcond=None)
        x = x + sol[:3]
    res = y - A @ sol
    by_sat = {ep.sats[j]: {"mean_m": float(res[jj == j].mean()), "std_m": float(res[jj == j].std()),
                           "samples": int((jj == j).sum())} for j in np.unique(jj)}
    return {"pos_ecef_m": x, "enu_error_m": ecef_to_enu(x, lat, lon, h), "rms_residual_m": float(np.sqrt(np.mean(res**2))),
            "by_satellite": by_sat, "epochs": int(epochs.size), "samples": int(kk.size)}


# ------------------------------------------------------------------ RTKLIB

RTKLIB_CONF = """pos1-posmode       =single
pos1-frequency     =l1
pos1-elmask        =10
pos1-ionoopt       =brdc
pos1-tropopt       =saas
pos1-navsys        =1
out-solformat      =xyz
out-timesys        =gpst
out-timeform       =tow
"""


def rnx2rtkp_path():
    return shutil.which("rnx2rtkp")


def run_rtklib(obs_path, nav_path, el_mask_deg: float = 10.0, ionoopt="brdc", tropopt="saas"):
    """RTKLIB's single-point ECEF solution: (t_sow (N,), xyz (N, 3)), or None if absent. L1 unless
    ionoopt is "dual-freq" (then L1+L2, RTKLIB's iono-free combination)."""
    exe = rnx2rtkp_path()
    if exe is None:
        return None
    conf = (RTKLIB_CONF.replace("=10", f"={el_mask_deg:g}").replace("=brdc", f"={ionoopt}")
            .replace("=saas", f"={tropopt}"))
    if ionoopt == "dual-freq":
        conf = conf.replace("pos1-frequency     =l1\n", "pos1-frequency     =l1+l2\n")
    with tempfile.TemporaryDirectory() as d:
        cf = Path(d) / "spp.conf"
        cf.write_text(conf)
        out = Path(d) / "out.pos"
        subprocess.run([exe, "-k", str(cf), "-o", str(out), str(obs_path), str(nav_path)], check=True,
                       capture_output=True, timeout=120)
        rows = []
        for ln in out.read_text().splitlines():
            if not ln.strip() or ln.startswith("%"):
                continue
            f = ln.split()
            rows.append([float(f[0]), float(f[1]), float(f[2]), float(f[3]), float(f[4])])
    a = np.array(rows)
    return a[:, 0] * 604800.0 + a[:, 1], a[:, 2:5]
