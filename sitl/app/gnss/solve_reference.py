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
    """RTKLIB's L1 single-point ECEF solution: (t_sow (N,), xyz (N, 3)), or None if absent."""
    exe = rnx2rtkp_path()
    if exe is None:
        return None
    conf = (RTKLIB_CONF.replace("=10", f"={el_mask_deg:g}").replace("=brdc", f"={ionoopt}")
            .replace("=saas", f"={tropopt}"))
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
