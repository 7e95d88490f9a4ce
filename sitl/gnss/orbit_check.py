"""Broadcast orbits and clocks checked against precise (IGS) orbits and clocks.

    res = check_orbits(read_nav(nav), read_sp3(sp3), read_clk(clk) or None)
    res.summary      # the JSON-ready figures (orbit_3d_rms_m, radial/along/cross, clock, SISRE ...)
    res.epochs       # per-(epoch, satellite) errors for plots

What is compared, per SP3 epoch and satellite of the nav file's systems (at the SP3 epochs
themselves: no interpolation of the precise orbit):
* the broadcast record in force (sitl.gnss.broadcast: IS-GPS-200 / GLONASS ICD RK4, PZ-90.02
  -> ITRF2000 shift for GLONASS). GPS: by default the record a receiver holds at t (the latest
  transmitted, ttm <= t, whose fit interval covers t; ``gps_select="transmitted"``); the
  figure with the record nearest in Toe is kept in ``record_selection``. A satellite-epoch
  whose record in force has a non-zero health flag is excluded and counted
  (``unhealthy_excluded``), never by its error; GPS records that are copies of another PRN's
  (``GpsEphemerides.mislabelled``) are left out and counted (``mislabelled_records``);
* reference points. GPS broadcast orbits refer to the antenna phase centre (APC) *as the
  control segment defines it*: the offsets NGA and the operational control segment use
  (``GPS_BROADCAST_APC_M``), not the IGS ones. IGS final orbits refer to the centre of mass
  (CoM); IGS clocks to the APC of the IGS antenna model (igs05.atx for GPS week 1590,
  ``IGS05_PCO_M``). The two APCs differ by metres (IIA: 0.95 vs ~2.5 m; IIR-A: ~1.6 vs ~1.2 m;
  IIR-B/M: ~0 vs ~0.7 m): the IGS z-offsets are estimated with the terrestrial frame's scale
  fixed and absorb it, the control segment's are the manufacturers'. With
  ``apc="control-segment"`` (default) the IGS CoM is moved to the control segment's APC by its
  full body-frame offset, x along the nominal yaw attitude (z toward the Earth's centre, y =
  z x sun, x = y x z: +x toward the sun's side; eclipse-season yaw manoeuvres not modelled),
  and the IGS clock to that point: c dt' = c dt_IGS + (z_IGS - z_CS) (the radial offset change
  goes into the clock, as in every orbit/clock estimation). ``apc="igs05"`` moves the CoM by
  the igs05.atx offsets instead (consistent with the IGS clocks as they are, not with the
  broadcast orbits); ``apc="none"`` corrects nothing (CoM, IGS clocks as they are). All three orbit figures are in
  ``reference_point``. GLONASS broadcast orbits refer to the CoM (Montenbruck et al. 2015,
  GPS Solutions 19:321), as IGS does: nothing is corrected;
* errors in the radial / along-track / cross-track frame of the precise orbit (along and
  cross from the inertial velocity, broadcast velocity + w_e x r);
* clocks: the broadcast polynomial af0 + af1 dt + af2 dt^2 without the relativistic term
  (IGS clocks exclude it) and without TGD (both refer to the P1/P2 ionosphere-free
  combination), minus the IGS clock (moved as above); the mean over the satellites of each
  epoch is removed (the offset of GPS time to IGS time, common to all satellites, does not
  reach a user). From the RINEX clock file when given (its epochs), else from the SP3 clocks;
* SISRE (Montenbruck et al. 2015, eq. 2): sqrt(rms(w_R dR - c dt)^2 + w_AC^2 (rms(dA)^2 +
  rms(dC)^2)), w_R = 0.98, w_AC^2 = 1/49 (GPS) or 1/45 (GLONASS), at the SP3 epochs with the
  SP3 clocks (common offset removed); ``sisre_orbit_m`` without the clock.
Not modelled: the broadcast frame WGS 84 (G1150) against IGS05 (cm: both are ITRF-aligned).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .broadcast import GPS_RECORD_SELECTIONS, broadcast_states
from .rinex_clk import ClockFile
from .rinex_common import GnssFileError
from .rinex_nav import NavFile
from .sp3 import Sp3

__all__ = ["APC_MODES", "GPS_BROADCAST_APC_M", "GPS_PCO_Z_2010", "GPS_SVN_BLOCK_2010", "IGS05_PCO_M",
           "OrbitCheck", "check_orbits", "nominal_yaw_axes", "sun_position_ecef_m"]

C = 299_792_458.0
OMEGA_E = 7.2921151467e-5
APC_MODES = ("control-segment", "igs05", "none")

#: GPS PRN -> (SVN, block) on 2010-07-01: the satellite antennas of igs05.atx whose VALID
#: FROM / UNTIL cover the day (RTKLIB's data/igs05.atx, github.com/tomojitakasu/RTKLIB).
GPS_SVN_BLOCK_2010 = {
    "G01": ("G049", "BLOCK IIR-M"), "G02": ("G061", "BLOCK IIR-B"), "G03": ("G033", "BLOCK IIA"),
    "G04": ("G034", "BLOCK IIA"), "G05": ("G050", "BLOCK IIR-M"), "G06": ("G036", "BLOCK IIA"),
    "G07": ("G048", "BLOCK IIR-M"), "G08": ("G038", "BLOCK IIA"), "G09": ("G039", "BLOCK IIA"),
    "G10": ("G040", "BLOCK IIA"), "G11": ("G046", "BLOCK IIR-A"), "G12": ("G058", "BLOCK IIR-M"),
    "G13": ("G043", "BLOCK IIR-A"), "G14": ("G041", "BLOCK IIR-A"), "G15": ("G055", "BLOCK IIR-M"),
    "G16": ("G056", "BLOCK IIR-A"), "G17": ("G053", "BLOCK IIR-M"), "G18": ("G054", "BLOCK IIR-A"),
    "G19": ("G059", "BLOCK IIR-B"), "G20": ("G051", "BLOCK IIR-A"), "G21": ("G045", "BLOCK IIR-A"),
    "G22": ("G047", "BLOCK IIR-B"), "G23": ("G060", "BLOCK IIR-B"), "G24": ("G024", "BLOCK IIA"),
    "G25": ("G062", "BLOCK IIF"), "G26": ("G026", "BLOCK IIA"), "G27": ("G027", "BLOCK IIA"),
    "G28": ("G044", "BLOCK IIR-A"), "G29": ("G057", "BLOCK IIR-M"), "G30": ("G030", "BLOCK IIA"),
    "G31": ("G052", "BLOCK IIR-M"), "G32": ("G023", "BLOCK IIA"),
}

#: igs05.atx satellite antenna offsets by SVN (body frame x, y, z, m; "NORTH / EAST / UP" of
#: the satellite entries): block x-offsets (IIA 0.279, IIF 0.394), satellite z-offsets. The
#: IGS final products of GPS week 1590 applied igs05_1585.atx (SP3 header "PCV:IGS05_1585").
IGS05_PCO_M = {
    "G049": (0.0, 0.0, 0.700), "G061": (0.0, 0.0, 0.614), "G033": (0.279, 0.0, 2.619),
    "G034": (0.279, 0.0, 2.279), "G050": (0.0, 0.0, 0.700), "G036": (0.279, 0.0, 2.676),
    "G048": (0.0, 0.0, 0.700), "G038": (0.279, 0.0, 2.405), "G039": (0.279, 0.0, 2.340),
    "G040": (0.279, 0.0, 2.389), "G046": (0.0, 0.0, 0.971), "G058": (0.0, 0.0, 0.700),
    "G043": (0.0, 0.0, 1.203), "G041": (0.0, 0.0, 1.178), "G055": (0.0, 0.0, 0.700),
    "G056": (0.0, 0.0, 1.307), "G053": (0.0, 0.0, 0.645), "G054": (0.0, 0.0, 1.133),
    "G059": (0.0, 0.0, 0.668), "G051": (0.0, 0.0, 1.154), "G045": (0.0, 0.0, 1.300),
    "G047": (0.0, 0.0, 0.792), "G060": (0.0, 0.0, 0.602), "G024": (0.279, 0.0, 2.455),
    "G062": (0.394, 0.0, 1.407), "G026": (0.279, 0.0, 2.307), "G027": (0.279, 0.0, 2.472),
    "G044": (0.0, 0.0, 0.911), "G057": (0.0, 0.0, 0.700), "G030": (0.279, 0.0, 2.466),
    "G052": (0.0, 0.0, 0.750), "G023": (0.279, 0.0, 2.575),
}

#: The antenna offsets the broadcast ephemerides refer to, by SVN (body frame x, y, z, m; CoM
#: -> APC): NGA's "GPS Ephemeris/Station/Antenna Offset Documentation" of August 2009
#: (earth-info.nga.mil/GandG/sathtml/gpsdoc2009_08a.html), whose per-PRN table (mm) is typed
#: here by the SVNs those PRNs had then (the same as on 2010-07-01 but PRN 25, then SVN 25).
#: Block IIA: the manufacturer's (0.2794, 0, 0.9519); IIR-A: Lockheed Martin's ~1.5-1.7 m;
#: IIR-B / IIR-M (the improved antenna panel): within 0.1 m of the CoM. No value for SVN 62
#: (the first IIF, launched 2010-05-28, unhealthy on 2010-07-01): none is applied there.
GPS_BROADCAST_APC_M = {
    "G049": (0.01245, -0.00038, -0.02283), "G061": (-0.00990, 0.00610, -0.08200),
    "G033": (0.2794, 0.0, 0.9519), "G034": (0.2794, 0.0, 0.9519), "G050": (0.00292, -0.00005, -0.01671),
    "G036": (0.2794, 0.0, 0.9519), "G048": (0.00127, 0.00025, 0.00056), "G038": (0.2794, 0.0, 0.9519),
    "G039": (0.2794, 0.0, 0.9519), "G040": (0.2794, 0.0, 0.9519), "G046": (0.00190, 0.00110, 1.51410),
    "G058": (-0.01016, 0.00587, -0.09355), "G043": (0.00240, 0.00250, 1.61400),
    "G041": (0.00180, 0.00020, 1.61370), "G055": (-0.00996, 0.00579, -0.01227),
    "G056": (-0.00980, 0.00600, 1.66300), "G053": (-0.00996, 0.00599, -0.10060),
    "G054": (-0.00980, 0.00600, 1.59230), "G059": (-0.00790, 0.00460, -0.01800),
    "G051": (0.00220, 0.00140, 1.61400), "G045": (0.00230, -0.00060, 1.58400),
    "G047": (0.00180, -0.00090, 0.05980), "G060": (-0.00880, 0.00350, 0.00040),
    "G024": (0.2794, 0.0, 0.9519), "G026": (0.2794, 0.0, 0.9519), "G027": (0.2794, 0.0, 0.9519),
    "G044": (0.00190, 0.00070, 1.51310), "G057": (-0.01012, 0.00591, -0.01512),
    "G030": (0.2794, 0.0, 0.9519), "G052": (0.00160, 0.00033, -0.05750), "G023": (0.2794, 0.0, 0.9519),
}

#: PRN: (SVN, block, igs05 z-offset) on 2010-07-01 (the earlier table's shape, kept for callers).
GPS_PCO_Z_2010 = {p: (svn, blk, IGS05_PCO_M[svn][2]) for p, (svn, blk) in GPS_SVN_BLOCK_2010.items()}
_PCO_VALID = (961977600.0 - 86400.0 * 30, 961977600.0 + 86400.0 * 30)  # 2010-07-01 +- 30 days

_SISRE_W = {"G": (0.98, 1.0 / 49.0), "R": (0.98, 1.0 / 45.0)}
_GPS_EPOCH_JD = 2444244.5  # 1980-01-06 00:00
_TT_MINUS_GPS_S = 51.184   # 19 s (TAI - GPS) + 32.184 s (TT - TAI)


def sun_position_ecef_m(t_gps_s) -> np.ndarray:
    """The Sun's position (..., 3), Earth-fixed, m, at GPS times: the low-precision series of
    Montenbruck & Gill (Satellite Orbits, 2000, sec. 3.3.2; ~0.1 deg), rotated by the GMST of
    the epoch (UT1 taken as GPS time: the 15 s of 2010 turn the Earth by 0.06 deg; precession
    and nutation, < 0.2 deg in 2010, are left out). Enough for the yaw attitude of a satellite."""
    t = np.asarray(t_gps_s, dtype=float)
    T = (_GPS_EPOCH_JD + (t + _TT_MINUS_GPS_S) / 86400.0 - 2451545.0) / 36525.0
    M = np.radians(357.5256 + 35999.049 * T)
    lam = np.radians(282.9400) + M + np.radians((6892.0 * np.sin(M) + 72.0 * np.sin(2 * M)) / 3600.0)
    r = (149.619 - 2.499 * np.cos(M) - 0.021 * np.cos(2 * M)) * 1e9
    eps = np.radians(23.43929111)
    x, y, z = r * np.cos(lam), r * np.sin(lam) * np.cos(eps), r * np.sin(lam) * np.sin(eps)
    gmst = np.radians((280.46061837 + 360.98564736629 * (_GPS_EPOCH_JD + t / 86400.0 - 2451545.0)) % 360.0)
    c, s = np.cos(gmst), np.sin(gmst)
    return np.stack([c * x + s * y, -s * x + c * y, z], axis=-1)


def nominal_yaw_axes(r_sat_m, t_gps_s):
    """Body axes (ex, ey, ez), each (N, 3), of satellites at ``r_sat_m`` (N, 3) under nominal yaw
    steering: ez toward the Earth's centre, ey = ez x e_sun / |.|, ex = ey x ez (+x toward the
    Sun's side), e_sun the unit vector satellite -> Sun."""
    r = np.asarray(r_sat_m, dtype=float)
    ez = -r / np.linalg.norm(r, axis=1)[:, None]
    es = sun_position_ecef_m(t_gps_s) - r
    es /= np.linalg.norm(es, axis=1)[:, None]
    ey = np.cross(ez, es)
    ey /= np.linalg.norm(ey, axis=1)[:, None]
    return np.cross(ey, ez), ey, ez


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


def _offsets(sats, table, letter="G"):
    """(N, 3) body-frame offsets of ``sats`` from ``table`` (by SVN) and (N,) bool: known."""
    off = np.zeros((len(sats), 3))
    known = np.zeros(len(sats), bool)
    for k, s in enumerate(sats):
        svn = GPS_SVN_BLOCK_2010.get(str(s), (None,))[0] if str(s).startswith(letter) else None
        if svn in table:
            off[k], known[k] = table[svn], True
    return off, known


def _figures(d):
    e3 = np.linalg.norm(d["d"], axis=1)
    return {"orbit_3d_rms_m": _rms(e3), "radial_rms_m": _rms(d["R"]), "along_rms_m": _rms(d["A"]),
            "cross_rms_m": _rms(d["C"]), "radial_mean_m": _mean(d["R"])}


def _errors(nav, sp3, sats, gps_select, with_tables):
    """Broadcast - precise at every SP3 epoch for ``sats``: the reference points' three
    variants (CoM, igs05 APC, control-segment APC), RAC-projected."""
    T, S = sp3.t_gps_s.size, sats.size
    cols = np.array([sp3.index(s) for s in sats])
    sat_q, t_q = np.tile(sats, T), np.repeat(sp3.t_gps_s, S)
    ref = sp3.pos_m[:, cols].reshape(-1, 3)
    st = broadcast_states(nav, sat_q, t_q, gps_select=gps_select)
    have_ref = np.isfinite(ref[:, 0])
    use = st.ok & have_ref & st.healthy
    r_ref = ref[use]
    out = {"st": st, "sat_q": sat_q, "t_q": t_q, "have_ref": have_ref, "use": use, "ref_clk": sp3.clock_s[:, cols].reshape(-1)}
    if not use.any():
        return out
    ex, ey, ez = nominal_yaw_axes(r_ref, t_q[use])
    rhat = -ez
    v_in = st.vel_m_s[use] + np.cross(np.array([0.0, 0.0, OMEGA_E]), st.pos_m[use])
    h = np.cross(r_ref, v_in)
    chat = h / np.linalg.norm(h, axis=1)[:, None]
    ahat = np.cross(chat, rhat)
    su = sat_q[use]
    zero = np.zeros((len(su), 3))
    tables = {"none": (zero, np.ones(len(su), bool))}
    if with_tables:
        tables["igs05"] = _offsets(su, IGS05_PCO_M)
        tables["control-segment"] = _offsets(su, GPS_BROADCAST_APC_M)
    else:
        tables["igs05"] = tables["control-segment"] = tables["none"]
    for mode, (off, known) in tables.items():
        apc = r_ref + off[:, 0:1] * ex + off[:, 1:2] * ey + off[:, 2:3] * ez
        d = st.pos_m[use] - apc
        out[mode] = {"d": d, "R": np.einsum("ij,ij->i", d, rhat), "A": np.einsum("ij,ij->i", d, ahat),
                     "C": np.einsum("ij,ij->i", d, chat), "off": off, "known": known}
    return out


_MAS_PER_RAD = 180.0 / np.pi * 3600e3


def helmert_fit(r_m, d_m) -> dict:
    """Least-squares 7-parameter Helmert fit d = T + w x r + s r of differences ``d_m`` (N, 3)
    at positions ``r_m`` (N, 3): translation (m), rotation (mas), scale (ppb) and the 3D RMS
    of what is left. A diagnostic (a fit), not a correction."""
    r = np.asarray(r_m, float)
    d = np.asarray(d_m, float)
    n = len(r)
    A = np.zeros((3 * n, 7))
    for k in range(3):
        A[k::3, k] = 1.0
    x, y, z = r[:, 0], r[:, 1], r[:, 2]
    A[0::3, 4], A[0::3, 5] = z, -y
    A[1::3, 3], A[1::3, 5] = -z, x
    A[2::3, 3], A[2::3, 4] = y, -x
    A[0::3, 6], A[1::3, 6], A[2::3, 6] = x, y, z
    p, *_ = np.linalg.lstsq(A, d.reshape(-1), rcond=None)
    left = (d.reshape(-1) - A @ p).reshape(-1, 3)
    return {"translation_m": [float(v) for v in p[:3]], "rotation_mas": [float(v * _MAS_PER_RAD) for v in p[3:6]],
            "scale_ppb": float(p[6] * 1e9), "orbit_3d_rms_m_after": _rms(np.linalg.norm(left, axis=1))}


def _clock_shift_s(sats, apc, with_tables):
    """What is added to an IGS clock (referred to the igs05 APC) to refer it to the APC of
    ``apc``: (z_IGS - z_apc) / c for GPS, 0 elsewhere or without tables."""
    if not with_tables or apc != "control-segment":
        return np.zeros(len(sats))
    z_igs = _offsets(sats, IGS05_PCO_M)[0][:, 2]
    z_cs, known = _offsets(sats, GPS_BROADCAST_APC_M)
    return np.where(known, (z_igs - z_cs[:, 2]) / C, 0.0)


def check_orbits(nav: NavFile, sp3: Sp3, clk: ClockFile | None = None, pco: bool = True,
                 apc: str = "control-segment", gps_select: str = "transmitted") -> OrbitCheck:
    """Compare the broadcast ephemerides of ``nav`` with ``sp3`` (and ``clk``); see the module
    docstring. ``apc``: the GPS reference point of the headline figures (``APC_MODES``;
    ``pco=False`` is ``apc="none"``); ``gps_select``: which GPS record is in force
    (sitl.gnss.broadcast). GnssFileError if no satellite of the nav file can be compared."""
    if apc not in APC_MODES:
        raise ValueError(f"apc: {apc!r} is not one of {', '.join(APC_MODES)}")
    if gps_select not in GPS_RECORD_SELECTIONS:
        raise ValueError(f"gps_select: {gps_select!r} is not one of {', '.join(GPS_RECORD_SELECTIONS)}")
    if not pco:
        apc = "none"
    systems = [s for s, e in (("G", nav.gps), ("R", nav.glonass)) if e is not None]
    sats = np.array([s for s in sp3.sats if s[0] in systems])
    if sats.size == 0:
        raise GnssFileError(sp3.path, None, f"no satellite of the navigation file's systems ({', '.join(systems)})")
    T, S = sp3.t_gps_s.size, sats.size
    with_tables = "G" in systems and _PCO_VALID[0] <= sp3.t_gps_s[0] <= _PCO_VALID[1]
    ev = _errors(nav, sp3, sats, gps_select, with_tables)
    st, sat_q, t_q, use, have_ref = ev["st"], ev["sat_q"], ev["t_q"], ev["use"], ev["have_ref"]
    if not use.any():
        raise GnssFileError(nav.path, None, "no healthy broadcast record in force at any epoch of the precise orbit")
    in_force = st.ok & have_ref
    unhealthy = in_force & ~st.healthy
    mislabelled = int(nav.gps.mislabelled().sum()) if nav.gps is not None else 0
    other_select = "nearest" if gps_select == "transmitted" else "transmitted"
    ev_other = _errors(nav, sp3, sats, other_select, with_tables) if "G" in systems else None

    head = ev[apc]
    d, R, A, Cr = head["d"], head["R"], head["A"], head["C"]
    e3 = np.linalg.norm(d, axis=1)
    su, tu = sat_q[use], t_q[use]

    # clocks at the SP3 epochs (for SISRE): broadcast polynomial without dt_r vs SP3 clock,
    # the IGS clock referred to the headline's reference point
    ref_clk = ev["ref_clk"]
    shift = np.zeros(T * S)
    shift[use] = _clock_shift_s(su, apc, with_tables)
    brd_poly = st.clock_s - st.relativistic_s
    cm = use & np.isfinite(ref_clk)
    dclk_sp3 = _demean_per_epoch(t_q[cm], brd_poly[cm] - (ref_clk[cm] + shift[cm]))
    # clock figure: from the clock file's epochs if given
    clock_source = "sp3"
    if clk is not None:
        clock_source = "clk"
        tc = np.repeat(clk.t_gps_s, S)
        scq = np.tile(sats, clk.t_gps_s.size)
        stc = broadcast_states(nav, scq, tc, gps_select=gps_select)
        rc = clk.bias_at(list(sats), clk.t_gps_s).reshape(-1)
        mc = stc.healthy & np.isfinite(rc)
        rc_moved = rc[mc] + _clock_shift_s(scq[mc], apc, with_tables)
        dclk = _demean_per_epoch(tc[mc], (stc.clock_s - stc.relativistic_s)[mc] - rc_moved)
        dclk_raw = _demean_per_epoch(tc[mc], (stc.clock_s - stc.relativistic_s)[mc] - rc[mc])
        dclk_sat = scq[mc]
        clock_span = [float(clk.t_gps_s[0]), float(clk.t_gps_s[-1])]
    else:
        dclk = dclk_sp3
        dclk_raw = _demean_per_epoch(t_q[cm], brd_poly[cm] - ref_clk[cm])
        dclk_sat = sat_q[cm]
        clock_span = [float(sp3.t_gps_s[0]), float(sp3.t_gps_s[-1])]

    # SISRE on the satellite-epochs with a clock
    sis_parts = []
    sis_orb = []
    idx_use = np.flatnonzero(use)
    pos_in_use = {k: j for j, k in enumerate(idx_use)}
    jj = np.array([pos_in_use[k] for k in np.flatnonzero(cm)], dtype=int)
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

    def block_of(s):
        return GPS_SVN_BLOCK_2010.get(str(s), (None, None))[1] if with_tables and str(s)[0] == "G" else None

    by_sat = {}
    for s in sats:
        m = su == s
        svn = GPS_SVN_BLOCK_2010.get(str(s), (None,))[0] if with_tables and s[0] == "G" else None
        entry = {"svn": svn, "block": block_of(s),
                 "epochs": int(m.sum()),
                 "unhealthy_excluded": int((unhealthy & (sat_q == s)).sum()),
                 "no_record_in_force": int((have_ref & ~st.ok & (sat_q == s)).sum()),
                 "orbit_3d_rms_m": _rms(e3[m]), "radial_rms_m": _rms(R[m]), "along_rms_m": _rms(A[m]),
                 "cross_rms_m": _rms(Cr[m]), "radial_mean_m": _mean(R[m]), "along_mean_m": _mean(A[m]),
                 "radial_mean_com_m": _mean(ev["none"]["R"][m]),
                 "radial_mean_igs05_apc_m": _mean(ev["igs05"]["R"][m]),
                 "radial_mean_control_segment_apc_m": _mean(ev["control-segment"]["R"][m]),
                 "apc_offset_m": [float(v) for v in head["off"][m][0]] if m.any() else None,
                 "apc_offset_known": bool(head["known"][m][0]) if m.any() else None,
                 "clock_rms_ns": _rms(dclk[dclk_sat == s] * 1e9)}
        by_sat[str(s)] = entry

    by_block = {}
    blocks = sorted({b for b in (block_of(s) for s in su) if b is not None})
    for b in blocks:
        m = np.array([block_of(s) == b for s in su])
        mc_ = np.array([block_of(s) == b for s in dclk_sat])
        by_block[b] = {"satellites": sorted(set(su[m].tolist())), "satellite_epochs": int(m.sum()),
                       **_figures({k: ev[apc][k][m] for k in ("d", "R", "A", "C")}),
                       "radial_mean_com_m": _mean(ev["none"]["R"][m]),
                       "radial_mean_igs05_apc_m": _mean(ev["igs05"]["R"][m]),
                       "orbit_3d_rms_com_m": _rms(np.linalg.norm(ev["none"]["d"][m], axis=1)),
                       "orbit_3d_rms_igs05_apc_m": _rms(np.linalg.norm(ev["igs05"]["d"][m], axis=1)),
                       "clock_mean_ns": _mean(dclk[mc_] * 1e9), "clock_rms_ns": _rms(dclk[mc_] * 1e9),
                       "clock_mean_igs_as_is_ns": _mean(dclk_raw[mc_] * 1e9)}

    def variant(mode):
        sel = {k: ev[mode][k] for k in ("d", "R", "A", "C")}
        return _figures(sel)

    apc_text = {
        "control-segment": ("IGS CoM moved to the control segment's APC (NGA offsets, x along the nominal yaw "
                            "attitude); IGS clocks moved to it by (z_IGS - z_CS)/c"),
        "igs05": "IGS CoM moved to the igs05.atx APC (x along the nominal yaw attitude); IGS clocks as they are",
        "none": "none: broadcast APC against the IGS CoM, IGS clocks as they are",
    }
    summary = {
        "nav": nav.path, "sp3": sp3.path, "clk": clk.path if clk is not None else None,
        "systems": systems,
        "epochs": int(T), "satellites_compared": int(len(set(su.tolist()))),
        "satellite_epochs": int(use.sum()),
        "orbit_3d_rms_m": _rms(e3), "radial_rms_m": _rms(R), "along_rms_m": _rms(A), "cross_rms_m": _rms(Cr),
        "radial_mean_m": _mean(R), "along_mean_m": _mean(A), "cross_mean_m": _mean(Cr),
        "clock_rms_ns": _rms(dclk * 1e9), "clock_source": clock_source,
        "clock_rms_ns_igs_clock_as_is": _rms(dclk_raw * 1e9),
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
        "record_selection": {
            "gps": gps_select,
            "rule": ("the latest transmitted record (ttm <= t) whose fit interval covers t: what a receiver holds"
                     if gps_select == "transmitted" else "the record whose Toe is nearest t within its fit interval"),
            f"orbit_3d_rms_m_{other_select}": (_rms(np.linalg.norm(ev_other[apc]["d"], axis=1))
                                               if ev_other is not None and ev_other["use"].any() else None),
        },
        "reference_point": {
            "broadcast": {"G": ("antenna phase centre of the control segment's antenna offsets (NGA table, "
                                "GPS_BROADCAST_APC_M)"), "R": "centre of mass"},
            "precise": {"orbits": "centre of mass",
                        "clocks": "antenna phase centre of igs05.atx (GPS; the IGS products' antenna model)"},
            "apc": apc if with_tables else "none",
            "correction": apc_text[apc] if with_tables and apc != "none" else "none",
            "offsets_for_the_date": bool(with_tables),
            "com": variant("none"), "igs05_apc": variant("igs05"), "control_segment_apc": variant("control-segment"),
            "uncorrected": variant("none"),
        },
        # what a frame difference would explain: the broadcast orbits' rotation about the IGS frame is
        # the control segment's Earth-orientation prediction error, which a user suffers; so a fit,
        # reported, never removed from the figures above
        "helmert_fit": dict(helmert_fit(ev["st"].pos_m[use] - d, d),
                            note="7-parameter Helmert fit of broadcast - precise (at the headline reference point); "
                                 "a diagnostic, not applied"),
        "by_block": by_block,
        "by_satellite": by_sat,
    }
    epochs = {"t_gps_s": tu, "sat": su, "err_3d_m": e3, "radial_m": R, "along_m": A, "cross_m": Cr}
    return OrbitCheck(summary, epochs)
