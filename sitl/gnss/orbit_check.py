"""Broadcast orbits and clocks checked against precise (IGS) orbits and clocks.

    res = check_orbits(read_nav(nav), read_sp3(sp3), read_clk(clk) or None)
    res.summary      # the JSON-ready figures (orbit_3d_rms_m, radial/along/cross, clock, SISRE ...)
    res.epochs       # per-(epoch, satellite) errors for plots

What is compared, per SP3 epoch and satellite of the nav file's systems:
* the broadcast record in force (sitl.gnss.broadcast: IS-GPS-200 / GLONASS ICD RK4, PZ-90.02
  -> ITRF2000 shift for GLONASS); a satellite-epoch whose record in force has a non-zero
  health flag is excluded and counted (``unhealthy_excluded``), never by its error; GPS
  records that are copies of another PRN's (``GpsEphemerides.mislabelled``) are left out
  and counted (``mislabelled_records``);
* reference points: broadcast GPS orbits refer to the antenna phase centre (APC), IGS finals
  to the centre of mass (CoM). The IGS CoM is moved to the APC by the satellite's z-offset of
  igs05.atx (the ANTEX the IGS05 finals were made with; ``GPS_PCO_Z_2010``), along the nadir
  (the x-offsets of Block IIA/IIF, 0.279 / 0.394 m in the body frame, depend on the yaw
  attitude and are not applied: they average out over an orbit). The uncorrected figures are
  kept in ``uncorrected``. GLONASS broadcast orbits refer to the CoM (Montenbruck et al. 2015,
  GPS Solutions 19:321), as IGS does: nothing is corrected;
* errors in the radial / along-track / cross-track frame of the precise orbit (along and
  cross from the inertial velocity, broadcast velocity + w_e x r);
* clocks: the broadcast polynomial af0 + af1 dt + af2 dt^2 without the relativistic term
  (IGS clocks exclude it) and without TGD (both refer to the P1/P2 ionosphere-free
  combination), minus the IGS clock; the mean over the satellites of each epoch is removed
  (the offset of GPS time to IGS time, common to all satellites, does not reach a user). From
  the RINEX clock file when given (its epochs), else from the SP3 clocks;
* SISRE (Montenbruck et al. 2015, eq. 2): sqrt(rms(w_R dR - c dt)^2 + w_AC^2 (rms(dA)^2 +
  rms(dC)^2)), w_R = 0.98, w_AC^2 = 1/49 (GPS) or 1/45 (GLONASS), at the SP3 epochs with the
  SP3 clocks (common offset removed); ``sisre_orbit_m`` without the clock.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .broadcast import broadcast_states
from .rinex_clk import ClockFile
from .rinex_common import GnssFileError
from .rinex_nav import NavFile
from .sp3 import Sp3

__all__ = ["GPS_PCO_Z_2010", "OrbitCheck", "check_orbits"]

C = 299_792_458.0
OMEGA_E = 7.2921151467e-5

#: GPS satellite antenna z-offsets (CoM -> APC along the nadir, m) in force on 2010-07-01:
#: PRN: (SVN, block, z) from igs05.atx ("TYPE / SERIAL NO" and "NORTH / EAST / UP" of each
#: satellite block whose VALID FROM/UNTIL covers 2010-07-01; the file as distributed in RTKLIB's
#: data/igs05.atx, github.com/tomojitakasu/RTKLIB, commit c033e62), typed in here.
GPS_PCO_Z_2010 = {
    "G01": ("G049", "BLOCK IIR-M", 0.700), "G02": ("G061", "BLOCK IIR-B", 0.614),
    "G03": ("G033", "BLOCK IIA", 2.619), "G04": ("G034", "BLOCK IIA", 2.279),
    "G05": ("G050", "BLOCK IIR-M", 0.700), "G06": ("G036", "BLOCK IIA", 2.676),
    "G07": ("G048", "BLOCK IIR-M", 0.700), "G08": ("G038", "BLOCK IIA", 2.405),
    "G09": ("G039", "BLOCK IIA", 2.340), "G10": ("G040", "BLOCK IIA", 2.389),
    "G11": ("G046", "BLOCK IIR-A", 0.971), "G12": ("G058", "BLOCK IIR-M", 0.700),
    "G13": ("G043", "BLOCK IIR-A", 1.203), "G14": ("G041", "BLOCK IIR-A", 1.178),
    "G15": ("G055", "BLOCK IIR-M", 0.700), "G16": ("G056", "BLOCK IIR-A", 1.307),
    "G17": ("G053", "BLOCK IIR-M", 0.645), "G18": ("G054", "BLOCK IIR-A", 1.133),
    "G19": ("G059", "BLOCK IIR-B", 0.668), "G20": ("G051", "BLOCK IIR-A", 1.154),
    "G21": ("G045", "BLOCK IIR-A", 1.300), "G22": ("G047", "BLOCK IIR-B", 0.792),
    "G23": ("G060", "BLOCK IIR-B", 0.602), "G24": ("G024", "BLOCK IIA", 2.455),
    "G25": ("G062", "BLOCK IIF", 1.407), "G26": ("G026", "BLOCK IIA", 2.307),
    "G27": ("G027", "BLOCK IIA", 2.472), "G28": ("G044", "BLOCK IIR-A", 0.911),
    "G29": ("G057", "BLOCK IIR-M", 0.700), "G30": ("G030", "BLOCK IIA", 2.466),
    "G31": ("G052", "BLOCK IIR-M", 0.750), "G32": ("G023", "BLOCK IIA", 2.575),
}
_PCO_VALID = (961977600.0 - 86400.0 * 30, 961977600.0 + 86400.0 * 30)  # 2010-07-01 +- 30 days

_SISRE_W = {"G": (0.98, 1.0 / 49.0), "R": (0.98, 1.0 / 45.0)}


@dataclass
class OrbitCheck:
    summary: dict
    epochs: dict  # t_gps_s (K,), sat (K,), err_3d_m, radial_m, along_m, cross_m (K,)


def _rms(x) -> float | None:
    x = np.asarray(x, float)
    return float(np.sqrt(np.mean(x * x))) if x.size else None


def _mean(x) -> float | None:
    x = np.asarray(x, float)
    return float(np.mean(x)) if x.size else None


def _demean_per_epoch(t, d):
    out = np.array(d, float)
    for tv in np.unique(t):
        m = t == tv
        out[m] -= out[m].mean()
    return out


def check_orbits(nav: NavFile, sp3: Sp3, clk: ClockFile | None = None, pco: bool = True) -> OrbitCheck:
    """Compare the broadcast ephemerides of ``nav`` with ``sp3`` (and ``clk``); see the module
    docstring. GnssFileError if no satellite of the nav file can be compared."""
    systems = [s for s, e in (("G", nav.gps), ("R", nav.glonass)) if e is not None]
    sats = np.array([s for s in sp3.sats if s[0] in systems])
    if sats.size == 0:
        raise GnssFileError(sp3.path, None, f"no satellite of the navigation file's systems ({', '.join(systems)})")
    cols = np.array([sp3.index(s) for s in sats])
    T, S = sp3.t_gps_s.size, sats.size
    sat_q = np.tile(sats, T)
    t_q = np.repeat(sp3.t_gps_s, S)
    ref = sp3.pos_m[:, cols].reshape(-1, 3)
    ref_clk = sp3.clock_s[:, cols].reshape(-1)
    st = broadcast_states(nav, sat_q, t_q)
    have_ref = np.isfinite(ref[:, 0])
    in_force = st.ok & have_ref
    unhealthy = in_force & ~st.healthy
    use = in_force & st.healthy
    if not use.any():
        raise GnssFileError(nav.path, None, "no healthy broadcast record in force at any epoch of the precise orbit")
    mislabelled = int(nav.gps.mislabelled().sum()) if nav.gps is not None else 0

    r_ref = ref[use]
    rhat = r_ref / np.linalg.norm(r_ref, axis=1)[:, None]
    z = np.zeros(len(r_ref))
    pco_applied = False
    if pco and "G" in systems and _PCO_VALID[0] <= sp3.t_gps_s[0] <= _PCO_VALID[1]:
        z = np.array([GPS_PCO_Z_2010.get(s, (None, None, 0.0))[2] if s[0] == "G" else 0.0 for s in sat_q[use]])
        pco_applied = True
    r_apc = r_ref - z[:, None] * rhat
    v_in = st.vel_m_s[use] + np.cross(np.array([0.0, 0.0, OMEGA_E]), st.pos_m[use])
    h = np.cross(r_ref, v_in)
    chat = h / np.linalg.norm(h, axis=1)[:, None]
    ahat = np.cross(chat, rhat)

    def rac(d):
        return (np.einsum("ij,ij->i", d, rhat), np.einsum("ij,ij->i", d, ahat), np.einsum("ij,ij->i", d, chat))

    d = st.pos_m[use] - r_apc
    d0 = st.pos_m[use] - r_ref
    R, A, Cr = rac(d)
    R0, A0, C0 = rac(d0)
    e3 = np.linalg.norm(d, axis=1)
    su, tu = sat_q[use], t_q[use]

    # clocks at the SP3 epochs (for SISRE): broadcast polynomial without dt_r vs SP3 clock
    brd_poly = st.clock_s - st.relativistic_s
    cm = use & np.isfinite(ref_clk)
    dclk_sp3 = _demean_per_epoch(t_q[cm], brd_poly[cm] - ref_clk[cm])
    # clock figure: from the clock file's epochs if given
    clock_source = "sp3"
    if clk is not None:
        clock_source = "clk"
        tc = np.repeat(clk.t_gps_s, S)
        scq = np.tile(sats, clk.t_gps_s.size)
        stc = broadcast_states(nav, scq, tc)
        rc = clk.bias_at(list(sats), clk.t_gps_s).reshape(-1)
        mc = stc.healthy & np.isfinite(rc)
        dclk = _demean_per_epoch(tc[mc], (stc.clock_s - stc.relativistic_s)[mc] - rc[mc])
        dclk_sat = scq[mc]
        clock_span = [float(clk.t_gps_s[0]), float(clk.t_gps_s[-1])]
    else:
        dclk, dclk_sat = dclk_sp3, t_q[cm] * 0 + 0  # placeholder replaced below
        dclk_sat = sat_q[cm]
        clock_span = [float(sp3.t_gps_s[0]), float(sp3.t_gps_s[-1])]

    # SISRE on the satellite-epochs with a clock
    sis_parts = []
    sis_orb = []
    idx_use = np.flatnonzero(use)
    pos_in_use = {k: j for j, k in enumerate(idx_use)}
    cm_idx = np.flatnonzero(cm)
    jj = np.array([pos_in_use[k] for k in cm_idx], dtype=int)
    for letter in systems:
        wr, wac2 = _SISRE_W[letter]
        ms = np.char.startswith(su, letter)
        if ms.any():
            sis_orb.append((wr**2 * np.mean(R[ms] ** 2) + wac2 * (np.mean(A[ms] ** 2) + np.mean(Cr[ms] ** 2)), ms.sum()))
        mj = np.char.startswith(su[jj], letter) if jj.size else np.zeros(0, bool)
        if mj.any():
            rr = wr * R[jj][mj] - C * dclk_sp3[mj]
            sis_parts.append((np.mean(rr**2) + wac2 * (np.mean(A[jj][mj] ** 2) + np.mean(Cr[jj][mj] ** 2)), mj.sum()))

    def pooled(parts):
        if not parts:
            return None
        n = sum(p[1] for p in parts)
        return float(np.sqrt(sum(p[0] * p[1] for p in parts) / n))

    by_sat = {}
    for s in sats:
        m = su == s
        entry = {"block": GPS_PCO_Z_2010.get(s, (None, None))[1] if pco_applied and s[0] == "G" else None,
                 "epochs": int(m.sum()),
                 "unhealthy_excluded": int((unhealthy & (sat_q == s)).sum()),
                 "no_record_in_force": int((have_ref & ~st.ok & (sat_q == s)).sum()),
                 "orbit_3d_rms_m": _rms(e3[m]), "radial_rms_m": _rms(R[m]), "along_rms_m": _rms(A[m]),
                 "cross_rms_m": _rms(Cr[m]), "radial_mean_m": _mean(R[m]),
                 "radial_mean_uncorrected_m": _mean(R0[m]),
                 "clock_rms_ns": _rms(dclk[dclk_sat == s] * 1e9), "pco_z_m": float(z[m][0]) if m.any() else None}
        by_sat[str(s)] = entry

    summary = {
        "nav": nav.path, "sp3": sp3.path, "clk": clk.path if clk is not None else None,
        "systems": systems,
        "epochs": int(T), "satellites_compared": int(len(set(su.tolist()))),
        "satellite_epochs": int(use.sum()),
        "orbit_3d_rms_m": _rms(e3), "radial_rms_m": _rms(R), "along_rms_m": _rms(A), "cross_rms_m": _rms(Cr),
        "radial_mean_m": _mean(R),
        "clock_rms_ns": _rms(dclk * 1e9), "clock_source": clock_source,
        # a precise file whose clocks are the broadcast ones (the IGS GLONASS orbits of 2009 carry
        # the broadcast clocks) is no reference for them: said, not hidden
        "clock_note": ("the reference clocks equal the broadcast ones (RMS < 0.01 ns): not an independent "
                       "reference, no clock figure is claimed") if dclk.size and _rms(dclk * 1e9) < 0.01 else None,
        "clock_span_gps_s": clock_span, "clock_samples": int(dclk.size),
        "clock_rms_ns_sp3_day": _rms(dclk_sp3 * 1e9),
        "sisre_m": pooled(sis_parts), "sisre_orbit_m": pooled(sis_orb),
        "unhealthy_excluded": int(unhealthy.sum()),
        "unhealthy_records_in_file": int(sum(int((e.health != 0).sum()) for e in (nav.gps, nav.glonass) if e is not None)),
        "mislabelled_records": mislabelled,
        "no_record_in_force": int((have_ref & ~st.ok).sum()),
        "no_precise_position": int((~have_ref).sum()),
        "reference_point": {
            "broadcast": {"G": "antenna phase centre", "R": "centre of mass"},
            "precise": "centre of mass",
            "correction": ("IGS CoM moved to the APC by the igs05.atx z-offset per satellite (GPS)"
                           if pco_applied else "none"),
            "uncorrected": {"orbit_3d_rms_m": _rms(np.linalg.norm(d0, axis=1)), "radial_rms_m": _rms(R0),
                            "along_rms_m": _rms(A0), "cross_rms_m": _rms(C0), "radial_mean_m": _mean(R0)},
        },
        "by_satellite": by_sat,
    }
    epochs = {"t_gps_s": tu, "sat": su, "err_3d_m": e3, "radial_m": R, "along_m": A, "cross_m": Cr}
    return OrbitCheck(summary, epochs)
