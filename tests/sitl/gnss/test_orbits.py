"""Tests of sitl.gnss.orbits: propagation against an independent two-body integration,
constellation layout, and the YUMA / RINEX loaders (round trips through tests/data)."""
from __future__ import annotations

import math
import pickle
from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from sitl.constants import F_GPS_L1_HZ, GM_GPS_M3_S2, OMEGA_E_GPS_RAD_S, PZ90_11, WGS84
from sitl.gnss.orbits import (
    DEFAULT_TOA_GPS_S,
    Constellation,
    default_constellation,
    glonass_constellation,
    gps_constellation,
    load_rinex_nav,
    load_yuma_almanac,
    sat_state_ecef,
)
from tests.helpers import rot_z as _rot_z

DATA = Path(__file__).resolve().parents[2] / "data"  # tests/data
WEEK_S = 604_800.0


def _gm_we(system):
    """Independent per-system constants: GPS ICD and PZ-90.11."""
    gm = np.where(system == "G", GM_GPS_M3_S2, PZ90_11.gm_m3_s2)
    we = np.where(system == "G", OMEGA_E_GPS_RAD_S, PZ90_11.omega_rad_s)
    return gm, we


def _eccentric_test_sats(toa):
    """A Molniya-like and a moderately eccentric orbit (harder Kepler solves)."""
    return Constellation(
        sat_id=["G90", "R90"], system=["G", "R"], toa_gps_s=toa, a_m=[26_560e3, 24_000e3],
        e=[0.72, 0.3], i_rad=np.radians([63.4, 30.0]), Omega0_rad=[1.0, -2.0],
        OmegaDot_rad_s=[-2e-9, 5e-9], omega_rad=np.radians([270.0, 10.0]), M0_rad=[0.3, 3.0],
        glonass_k=[0, -7],
    )


# ---------------------------------------------------------------------------
# Propagation
# ---------------------------------------------------------------------------

def test_positions_match_independent_two_body_integration():
    """The ICD model is a two-body orbit seen from a frame rotating at w_e - OmegaDot
    about z.  Integrate r'' = -GM r/|r|^3 in inertial space from the state at t0 for
    2 h (DOP853, rtol 1e-12) and rotate into that frame."""
    base = default_constellation()
    c = base.subset(np.arange(0, len(base), 5)).concat(_eccentric_test_sats(DEFAULT_TOA_GPS_S))
    gm, we = _gm_we(c.system)
    w_eff = we - c.OmegaDot_rad_s
    t0 = DEFAULT_TOA_GPS_S + 1234.0
    p0, v0 = sat_state_ecef(c, t0)
    t_rel = np.arange(0.0, 7200.0 + 1.0, 600.0)
    p_model, v_model = sat_state_ecef(c, t0 + t_rel)
    for j in range(len(c)):
        r_i0 = p0[j]
        v_i0 = v0[j] + w_eff[j] * np.array([-p0[j, 1], p0[j, 0], 0.0])

        def rhs(_, y, mu=gm[j]):
            r = y[:3]
            return np.concatenate([y[3:], -mu * r / np.linalg.norm(r) ** 3])

        sol = solve_ivp(rhs, (0.0, t_rel[-1]), np.concatenate([r_i0, v_i0]), method="DOP853",
                        t_eval=t_rel, rtol=1e-12, atol=1e-6)
        assert sol.success
        r_i, v_i = sol.y[:3].T, sol.y[3:].T
        ang = w_eff[j] * t_rel
        p_ref = _rot_z(ang, r_i)
        v_ref = _rot_z(ang, v_i) - w_eff[j] * np.stack([-p_ref[:, 1], p_ref[:, 0], 0 * ang], axis=-1)
        err_p = np.linalg.norm(p_model[:, j] - p_ref, axis=-1).max()
        err_v = np.linalg.norm(v_model[:, j] - v_ref, axis=-1).max()
        assert err_p < 1e-2, (c.sat_id[j], err_p)  # requirement is 1 m; typically ~1e-5 m
        assert err_v < 1e-5, (c.sat_id[j], err_v)


def _harmonic_constellation():
    base = gps_constellation().subset(["G01", "G07", "G13"])
    n = len(base)
    return base.replace(
        delta_n_rad_s=np.full(n, 4.6e-9), idot_rad_s=np.full(n, -3.5e-10),
        cuc_rad=np.full(n, -2.7e-6), cus_rad=np.full(n, 1.3e-7 * 50), crc_m=np.full(n, 386.6),
        crs_m=np.full(n, -54.6), cic_rad=np.full(n, -8.9e-8), cis_rad=np.full(n, 1.3e-7),
    )


@pytest.mark.parametrize("which", ["builtin", "eccentric", "harmonic"])
def test_velocity_is_derivative_of_position(which):
    c = {"builtin": default_constellation(), "eccentric": _eccentric_test_sats(DEFAULT_TOA_GPS_S),
         "harmonic": _harmonic_constellation()}[which]
    h = 2.0**-3  # exact in float64 next to an integer epoch
    t = DEFAULT_TOA_GPS_S + 3600.0 + np.array([-h, 0.0, h])
    p, v = sat_state_ecef(c, t)
    fd = (p[2] - p[0]) / (2 * h)
    assert np.abs(fd - v[1]).max() < 1e-5


def _icd_reference(el, t):
    """Scalar transliteration of IS-GPS-200 Table 20-IV (position only)."""
    gm = GM_GPS_M3_S2 if el["system"] == "G" else PZ90_11.gm_m3_s2
    we = OMEGA_E_GPS_RAD_S if el["system"] == "G" else PZ90_11.omega_rad_s
    tk = t - el["toa_gps_s"]
    n = math.sqrt(gm / el["a_m"] ** 3) + el["delta_n_rad_s"]
    M = el["M0_rad"] + n * tk
    e = el["e"]
    E = M
    for _ in range(50):
        E = E - (E - e * math.sin(E) - M) / (1 - e * math.cos(E))
    nu = math.atan2(math.sqrt(1 - e * e) * math.sin(E), math.cos(E) - e)
    phi = nu + el["omega_rad"]
    u = phi + el["cus_rad"] * math.sin(2 * phi) + el["cuc_rad"] * math.cos(2 * phi)
    r = el["a_m"] * (1 - e * math.cos(E)) + el["crs_m"] * math.sin(2 * phi) + el["crc_m"] * math.cos(2 * phi)
    i = el["i_rad"] + el["idot_rad_s"] * tk + el["cis_rad"] * math.sin(2 * phi) + el["cic_rad"] * math.cos(2 * phi)
    toe = el["toa_gps_s"] % WEEK_S
    Om = el["Omega0_rad"] + (el["OmegaDot_rad_s"] - we) * tk - we * toe
    xp, yp = r * math.cos(u), r * math.sin(u)
    return np.array([xp * math.cos(Om) - yp * math.cos(i) * math.sin(Om),
                     xp * math.sin(Om) + yp * math.cos(i) * math.cos(Om), yp * math.sin(i)])


@pytest.mark.parametrize("which", ["builtin", "harmonic"])
def test_positions_match_scalar_icd_algorithm(which):
    c = default_constellation() if which == "builtin" else _harmonic_constellation()
    names = ["system", "toa_gps_s", "a_m", "e", "i_rad", "Omega0_rad", "OmegaDot_rad_s", "omega_rad", "M0_rad",
             "delta_n_rad_s", "idot_rad_s", "cuc_rad", "cus_rad", "crc_m", "crs_m", "cic_rad", "cis_rad"]
    for t in DEFAULT_TOA_GPS_S + np.array([-5000.0, 0.0, 12345.5, 86400.0 * 3]):
        p, _ = sat_state_ecef(c, t)
        for j in range(len(c)):
            el = {k: getattr(c, k)[j] for k in names}
            assert np.linalg.norm(p[j] - _icd_reference(el, t)) < 1e-5


def test_shapes():
    c = default_constellation()
    S = len(c)
    p, v = sat_state_ecef(c, DEFAULT_TOA_GPS_S)
    assert p.shape == v.shape == (S, 3)
    t = DEFAULT_TOA_GPS_S + np.arange(6.0).reshape(2, 3) * 100
    p2, v2 = sat_state_ecef(c, t)
    assert p2.shape == v2.shape == (2, 3, S, 3)
    p3, _ = sat_state_ecef(c, t[1, 2])
    assert np.array_equal(p2[1, 2], p3)
    assert p2.flags.c_contiguous
    with pytest.raises(ValueError, match="t_gps_s"):
        sat_state_ecef(c, np.nan)
    with pytest.raises(ValueError, match="constellation"):
        sat_state_ecef("GPS", 0.0)


def test_radius_period_inclination():
    c = default_constellation()
    gm, we = _gm_we(c.system)
    t = DEFAULT_TOA_GPS_S + np.linspace(0, 86400, 97)
    p, _ = sat_state_ecef(c, t)
    r = np.linalg.norm(p, axis=-1)
    assert np.all(r >= c.a_m * (1 - c.e) - 1e-3) and np.all(r <= c.a_m * (1 + c.e) + 1e-3)
    # Period: the inertial position (frame rotating at w_e - OmegaDot undone) repeats.
    T = 2 * np.pi / np.sqrt(gm / c.a_m**3)
    w_eff = we - c.OmegaDot_rad_s
    t0 = DEFAULT_TOA_GPS_S + 100.0
    p0, _ = sat_state_ecef(c, t0)
    for j in range(len(c)):
        pT, _ = sat_state_ecef(c.subset([j]), t0 + T[j])
        back = _rot_z(-w_eff[j] * T[j], pT[0])
        assert np.linalg.norm(back - p0[j]) < 1e-3
    assert 11.9 * 3600 < T[c.system == "G"].mean() < 12.0 * 3600  # half a sidereal day
    assert abs(T[c.system == "R"].mean() - (11 * 3600 + 15 * 60 + 44)) < 60  # 11 h 15 min 44 s
    # Inclination from the inertial angular momentum.
    p0, v0 = sat_state_ecef(c, t0)
    v_in = v0 + w_eff[:, None] * np.stack([-p0[:, 1], p0[:, 0], 0 * p0[:, 0]], axis=-1)
    hvec = np.cross(p0, v_in)
    inc = np.degrees(np.arccos(hvec[:, 2] / np.linalg.norm(hvec, axis=-1)))
    assert np.allclose(inc[c.system == "G"], 55.0, atol=1e-9)
    assert np.allclose(inc[c.system == "R"], 64.8, atol=1e-9)


def _node_longitudes_deg(c, t):
    """Earth-fixed longitude of each ascending node from the angular momentum."""
    gm, we = _gm_we(c.system)
    p, v = sat_state_ecef(c, t)
    w_eff = we - c.OmegaDot_rad_s
    v_in = v + w_eff[:, None] * np.stack([-p[:, 1], p[:, 0], 0 * p[:, 0]], axis=-1)
    hv = np.cross(p, v_in)
    return np.degrees(np.arctan2(hv[:, 0], -hv[:, 1])) % 360.0


def _cluster_planes(node_deg, tol=1.0):
    planes = []
    for lon in node_deg:
        for pl in planes:
            if abs((lon - pl[0] + 180) % 360 - 180) < tol:
                pl[1] += 1
                break
        else:
            planes.append([lon, 1])
    return sorted(planes)


def test_gps_layout():
    c = gps_constellation()
    assert 27 <= len(c) <= 32 and len(c) == 31
    assert np.all(c.system == "G") and np.all(c.glonass_k == 0)
    assert np.allclose(c.a_m, 26_559_700.0)
    assert np.all(c.e < 0.03)
    planes = _cluster_planes(_node_longitudes_deg(c, DEFAULT_TOA_GPS_S))
    assert len(planes) == 6
    lons = np.array([p[0] for p in planes])
    gaps = np.diff(np.concatenate([lons, [lons[0] + 360]]))
    assert np.allclose(gaps, 60.0, atol=1e-6)
    counts = [p[1] for p in planes]
    assert min(counts) >= 4 and max(counts) <= 6 and sum(counts) == 31
    assert c.OmegaDot_rad_s.max() < -7e-9 and c.OmegaDot_rad_s.min() > -9e-9  # J2 node regression


def test_glonass_layout_and_channels():
    c = glonass_constellation()
    assert len(c) == 24
    assert list(c.sat_id) == [f"R{j:02d}" for j in range(1, 25)]
    assert np.allclose(c.a_m, 25_510_000.0)
    planes = _cluster_planes(_node_longitudes_deg(c, DEFAULT_TOA_GPS_S))
    assert [p[1] for p in planes] == [8, 8, 8]
    lons = np.array([p[0] for p in planes])
    assert np.allclose(np.diff(np.concatenate([lons, [lons[0] + 360]])), 120.0, atol=1e-6)
    k = c.glonass_k
    assert k.min() >= -7 and k.max() <= 6
    p, _ = sat_state_ecef(c, DEFAULT_TOA_GPS_S + 777.0)
    for plane in range(3):
        for j in range(4):
            a, b = 8 * plane + j, 8 * plane + j + 4
            assert k[a] == k[b]  # antipodal slots share a channel
            assert np.linalg.norm(p[a] + p[b]) < 1e-3  # and are antipodal
        for j in range(7):
            a, b = 8 * plane + j, 8 * plane + j + 1
            cosang = p[a] @ p[b] / np.linalg.norm(p[a]) / np.linalg.norm(p[b])
            assert abs(np.degrees(np.arccos(cosang)) - 45.0) < 1e-6
    # Real channel table (R01..R08 in plane 1).
    assert list(k[:8]) == [1, -4, 5, 6, 1, -4, 5, 6]
    # All 12 distinct channels of the table are used exactly twice.
    vals, counts = np.unique(k, return_counts=True)
    assert np.all(counts == 2) and len(vals) == 12


def test_carrier_frequencies():
    c = default_constellation()
    f = c.carrier_l1_hz
    assert np.all(f[c.system == "G"] == F_GPS_L1_HZ)
    glo = c.system == "R"
    assert np.allclose(f[glo], 1602e6 + c.glonass_k[glo] * 0.5625e6, rtol=0, atol=1e-3)
    assert f[list(c.sat_id).index("R01")] == 1602.5625e6
    assert f[list(c.sat_id).index("R10")] == 1602e6 - 7 * 0.5625e6


def _site(lat_deg, lon_deg, h_m=0.0):
    """WGS-84 geodetic -> ECEF and the local up unit vector (own formula)."""
    la, lo = np.radians(lat_deg), np.radians(lon_deg)
    n = WGS84.a_m / np.sqrt(1 - WGS84.e2 * np.sin(la) ** 2)
    pos = np.array([(n + h_m) * np.cos(la) * np.cos(lo), (n + h_m) * np.cos(la) * np.sin(lo),
                    (n * (1 - WGS84.e2) + h_m) * np.sin(la)])
    up = np.array([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)])
    return pos, up


@pytest.mark.parametrize("lat,lon", [(0.0, 0.0), (45.0, 7.0), (-33.9, 151.2), (64.8, -147.7), (-70.0, 30.0)])
def test_at_least_four_of_each_system_visible(lat, lon):
    c = default_constellation()
    pos, up = _site(lat, lon)
    t = DEFAULT_TOA_GPS_S + np.arange(0.0, 86400.0, 3 * 3600.0 + 17.0)
    p, _ = sat_state_ecef(c, t)
    d = p - pos
    el = np.degrees(np.arcsin((d @ up) / np.linalg.norm(d, axis=-1)))
    for system in "GR":
        assert (el[:, c.system == system] > 10.0).sum(axis=1).min() >= 4


# ---------------------------------------------------------------------------
# Constellation container
# ---------------------------------------------------------------------------

def test_subset_concat_len_and_validation():
    c = default_constellation()
    assert len(c) == 55
    assert len(default_constellation("G")) == 31 and len(default_constellation("R")) == 24
    assert list(default_constellation("RG").sat_id[:2]) == ["R01", "R02"]
    s = c.subset(["R07", "G01"])
    assert list(s.sat_id) == ["R07", "G01"] and s.glonass_k[0] == 5
    assert len(c.subset(c.system == "R")) == 24
    assert len(c.subset("G05")) == 1
    assert list(c.subset([0, 2]).sat_id) == ["G01", "G03"]
    g, r = c.subset(c.system == "G"), c.subset(c.system == "R")
    both = g.concat(r)
    assert len(both) == 55 and np.array_equal(both.sat_id, c.sat_id)
    p1, _ = sat_state_ecef(both, DEFAULT_TOA_GPS_S + 10)
    p2, _ = sat_state_ecef(c, DEFAULT_TOA_GPS_S + 10)
    assert np.array_equal(p1, p2)
    with pytest.raises(ValueError, match="mask_or_ids"):
        c.subset(["G04"])  # no PRN 4 in the layout
    with pytest.raises(ValueError, match="mask_or_ids"):
        c.subset(np.ones(3, bool))
    with pytest.raises(ValueError, match="sat_id"):
        g.concat(g)
    with pytest.raises(ValueError, match="e:"):
        g.replace(e=np.full(len(g), 1.2))
    with pytest.raises(ValueError, match="a_m"):
        g.replace(a_m=np.ones(3))
    with pytest.raises(ValueError, match="glonass_k"):
        r.replace(glonass_k=np.full(24, 9))
    with pytest.raises(ValueError, match="system"):
        Constellation(sat_id=["E01"], system=["E"], toa_gps_s=0, a_m=2.9e7, e=0, i_rad=1, Omega0_rad=0,
                      OmegaDot_rad_s=0, omega_rad=0, M0_rad=0, glonass_k=0)
    with pytest.raises(ValueError, match="systems"):
        default_constellation("GE")
    with pytest.raises(ValueError):
        c.sat_id[0] = "G99"  # read-only arrays
    c_copy = pickle.loads(pickle.dumps(c))
    assert np.array_equal(c_copy.M0_rad, c.M0_rad) and not c_copy.M0_rad.flags.writeable
    gm, we = _gm_we(c.system)
    assert np.array_equal(c.gm_m3_s2, gm) and np.array_equal(c.omega_e_rad_s, we)


def test_toa_changes_epoch_not_geometry():
    """Built-ins are defined at their toa: same Earth-fixed geometry at t = toa."""
    a = gps_constellation(toa_gps_s=1000 * WEEK_S + 12345.0)
    b = gps_constellation()
    pa, _ = sat_state_ecef(a, 1000 * WEEK_S + 12345.0)
    pb, _ = sat_state_ecef(b, DEFAULT_TOA_GPS_S)
    assert np.abs(pa - pb).max() < 1e-6


# ---------------------------------------------------------------------------
# Loaders (sample files were written from KNOWN by the writers below)
# ---------------------------------------------------------------------------

KNOWN_TOA_GPS_S = 2347 * WEEK_S + 319_488.0  # 2025-01-01 16:44:48 GPS time
KNOWN = Constellation(
    sat_id=["G02", "G07", "G31"], system=["G", "G", "G"], toa_gps_s=KNOWN_TOA_GPS_S,
    a_m=[5153.629883**2, 5153.644531**2, 5153.560059**2],
    e=[0.01778459549, 0.01116085052, 0.008842945099],
    i_rad=[0.9491769778, 0.9595073797, 0.9642051958],
    Omega0_rad=[-0.8051818717, 2.408955040, 2.421005178],
    OmegaDot_rad_s=[-7.908900866e-9, -7.737465154e-9, -7.714607059e-9],
    omega_rad=[-1.897790397, -2.544183911, -0.156421849],
    M0_rad=[-2.727285640, 2.483729488, 2.278999603],
    glonass_k=0,
    delta_n_rad_s=[4.646979279625e-9, 5.0e-9, 4.2e-9], idot_rad_s=[-3.5e-10, 2.1e-10, 0.0],
    cuc_rad=[-2.680346369743e-6, 1.0e-6, 0.0], cus_rad=[1.266598701477e-7 * 50, 7.0e-6, 0.0],
    crc_m=[386.5625, 210.25, 0.0], crs_m=[-54.5625, 12.5, 0.0],
    cic_rad=[-8.940696716309e-8, 3.0e-8, 0.0], cis_rad=[1.285225152969e-7, -6.0e-8, 0.0],
)
KNOWN_HEALTH = [0, 0, 63]


def _yuma_num(x):
    """YUMA style: 0.dddddddddd E+xx mantissa below 1."""
    if x == 0:
        return " 0.0000000000E+000"
    ex = math.floor(math.log10(abs(x))) + 1
    m = x / 10.0**ex
    if abs(round(m, 10)) >= 1.0:
        m, ex = m / 10, ex + 1
    return f"{m: .10f}E{ex:+04d}"


def write_yuma(c, health, path):
    out = []
    for j in range(len(c)):
        prn = int(c.sat_id[j][1:])
        week = int(c.toa_gps_s[j] // WEEK_S)
        toa = c.toa_gps_s[j] - week * WEEK_S
        out += [
            f"******** Week {week % 1024} almanac for PRN-{prn:02d} ********",
            f"ID:                         {prn:02d}",
            f"Health:                     {health[j]:03d}",
            f"Eccentricity:              {_yuma_num(c.e[j])}",
            f"Time of Applicability(s):  {toa:.4f}",
            f"Orbital Inclination(rad):   {c.i_rad[j]:.10f}",
            f"Rate of Right Ascen(r/s):  {_yuma_num(c.OmegaDot_rad_s[j])}",
            f"SQRT(A)  (m 1/2):           {math.sqrt(c.a_m[j]):.6f}",
            f"Right Ascen at Week(rad):  {_yuma_num(c.Omega0_rad[j])}",
            f"Argument of Perigee(rad):  {c.omega_rad[j]: .9f}",
            f"Mean Anom(rad):            {_yuma_num(c.M0_rad[j])}",
            f"Af0(s):                    {_yuma_num(1.2e-5 * (j + 1))}",
            f"Af1(s/s):                  {_yuma_num(-3.637978807e-12)}",
            f"week:                        {week % 1024}",
            "",
        ]
    Path(path).write_text("\n".join(out))


def _d19(x):
    """RINEX D19.12 field."""
    s = f"{x:19.12E}"
    return s.replace("E", "D")


def _rinex_record_lines(c, j, health, version):
    week = int(c.toa_gps_s[j] // WEEK_S)
    toe = c.toa_gps_s[j] - week * WEEK_S
    prn = int(c.sat_id[j][1:])
    sqrt_a = math.sqrt(c.a_m[j])
    rows = [
        [7.0 + j, c.crs_m[j], c.delta_n_rad_s[j], c.M0_rad[j]],
        [c.cuc_rad[j], c.e[j], c.cus_rad[j], sqrt_a],
        [toe, c.cic_rad[j], c.Omega0_rad[j], c.cis_rad[j]],
        [c.i_rad[j], c.crc_m[j], c.omega_rad[j], c.OmegaDot_rad_s[j]],
        [c.idot_rad_s[j], 1.0, float(week), 0.0],
        [2.0, float(health[j]), -1.1e-8, 7.0 + j],
        [toe - 30.0, 4.0],
    ]
    clock = _d19(-2.7e-5) + _d19(-3.6e-12) + _d19(0.0)
    # toc = toe as a calendar date: 2025-01-01 00:00 is second 259200 of week 2347.
    sec = int(toe - 259_200.0)
    hh, mm, ss = sec // 3600, sec % 3600 // 60, sec % 60
    if version == 3:
        first = f"G{prn:02d} 2025 01 01 {hh:02d} {mm:02d} {ss:02d}" + clock
        pad = "    "
    else:
        first = f"{prn:2d} 25  1  1 {hh:2d} {mm:2d}{ss:5.1f}" + clock
        pad = "   "
    return [first] + [pad + "".join(_d19(v) for v in row) for row in rows]


def write_rinex(c, health, path, version):
    if version == 3:
        head = [
            f"{'3.04':>9s}{'':11s}{'N: GNSS NAV DATA':20s}{'M: MIXED':20s}RINEX VERSION / TYPE",
            f"{'skyfuse tests':20s}{'skyfuse':20s}{'20250101 000000 UTC':20s}PGM / RUN BY / DATE",
            f"{'':60s}END OF HEADER",
        ]
    else:
        head = [
            f"{'2.11':>9s}{'':11s}{'N: GPS NAV DATA':20s}{'':20s}RINEX VERSION / TYPE",
            f"{'skyfuse tests':20s}{'skyfuse':20s}{'20250101 000000 UTC':20s}PGM / RUN BY / DATE",
            f"{'':60s}END OF HEADER",
        ]
    body = []
    for j in range(len(c)):
        body += _rinex_record_lines(c, j, health, version)
        if version == 3 and j == 0:
            # A GLONASS record (4 lines) to be skipped by the loader.
            body += ["R07 2025 01 01 00 15 00" + _d19(1e-5) + _d19(0.0) + _d19(5.4e4)]
            body += ["    " + "".join(_d19(v) for v in (1.2e4, -1.5, 0.0, 0.0)) for _ in range(3)]
    if version == 3:
        # A second, later G02 record: only the first record per satellite is used.
        later = _rinex_record_lines(c.replace(M0_rad=c.M0_rad + 1.0), 0, health, version)
        body += later
    Path(path).write_text("\n".join(head + body) + "\n")


def _compare(loaded, ref, rtol):
    """Elements equal to the printed precision (angles also to 1e-9 rad absolute)."""
    assert list(loaded.sat_id) == list(ref.sat_id)
    for name in ("toa_gps_s", "a_m", "e", "i_rad", "Omega0_rad", "OmegaDot_rad_s", "omega_rad", "M0_rad"):
        atol = 1e-9 if name in ("i_rad", "Omega0_rad", "omega_rad", "M0_rad") else 0.0
        assert np.allclose(getattr(loaded, name), getattr(ref, name), rtol=rtol, atol=atol), name


def test_yuma_sample_file_known_values():
    c = load_yuma_almanac(DATA / "yuma_sample.alm")
    ref = KNOWN.replace(**{k: np.zeros(3) for k in ("delta_n_rad_s", "idot_rad_s", "cuc_rad", "cus_rad",
                                                    "crc_m", "crs_m", "cic_rad", "cis_rad")})
    _compare(c, ref, rtol=2e-9)
    assert c.toa_gps_s[0] == 2347 * WEEK_S + 319_488.0  # week 299 (mod 1024) -> 2347
    assert c.e[1] == pytest.approx(0.01116085052, abs=1e-12)
    p, _ = sat_state_ecef(c, KNOWN_TOA_GPS_S + 3600)
    p_ref, _ = sat_state_ecef(ref, KNOWN_TOA_GPS_S + 3600)
    assert np.abs(p - p_ref).max() < 0.1
    assert len(load_yuma_almanac(DATA / "yuma_sample.alm", healthy_only=True)) == 2


def test_yuma_round_trip(tmp_path):
    ref = gps_constellation().subset(np.arange(0, 31, 3))
    path = tmp_path / "alm.txt"
    write_yuma(ref, [0] * len(ref), path)
    c = load_yuma_almanac(path)
    _compare(c, ref, rtol=1e-9)
    # Week resolution around another epoch: 10-bit week 299 near 2005 -> 1323.
    c2 = load_yuma_almanac(path, reference_t_gps_s=1323 * WEEK_S)
    assert np.allclose(c2.toa_gps_s - c.toa_gps_s, -1024 * WEEK_S)


@pytest.mark.parametrize("name", ["rinex3_sample.rnx", "rinex2_sample.25n"])
def test_rinex_sample_files_known_values(name):
    c = load_rinex_nav(DATA / name)
    _compare(c, KNOWN, rtol=1e-11)
    for k in ("delta_n_rad_s", "idot_rad_s", "cuc_rad", "cus_rad", "crc_m", "crs_m", "cic_rad", "cis_rad"):
        assert np.allclose(getattr(c, k), getattr(KNOWN, k), rtol=1e-11, atol=1e-300), k
    p, v = sat_state_ecef(c, KNOWN_TOA_GPS_S + 1800)
    p_ref, v_ref = sat_state_ecef(KNOWN, KNOWN_TOA_GPS_S + 1800)
    assert np.abs(p - p_ref).max() < 1e-4 and np.abs(v - v_ref).max() < 1e-7
    plain = load_rinex_nav(DATA / name, harmonics=False)
    assert np.all(plain.crc_m == 0) and np.all(plain.delta_n_rad_s == 0)
    assert list(load_rinex_nav(DATA / name, healthy_only=True).sat_id) == ["G02", "G07"]


@pytest.mark.parametrize("version", [2, 3])
def test_rinex_round_trip(tmp_path, version):
    ref = _harmonic_constellation().concat(gps_constellation().subset(["G20", "G32"]))
    path = tmp_path / f"nav{version}.rnx"
    write_rinex(ref, [0] * len(ref), path, version)
    c = load_rinex_nav(path)
    _compare(c, ref, rtol=1e-11)


def _corrupt(src, dst, lineno, new_text):
    lines = Path(src).read_text().splitlines()
    lines[lineno - 1] = new_text
    Path(dst).write_text("\n".join(lines) + "\n")


def test_malformed_files_raise_with_file_and_line(tmp_path):
    bad = tmp_path / "bad.alm"
    _corrupt(DATA / "yuma_sample.alm", bad, 4, "Eccentricity:               0.17E-00X")
    with pytest.raises(ValueError, match=r"bad\.alm, line 4"):
        load_yuma_almanac(bad)
    _corrupt(DATA / "yuma_sample.alm", bad, 6, "Orbital Inclination(rad)    0.9491769778")
    with pytest.raises(ValueError, match=r"bad\.alm, line 6"):
        load_yuma_almanac(bad)
    _corrupt(DATA / "yuma_sample.alm", bad, 8, "Bogus key:                  1.0")
    with pytest.raises(ValueError, match=r"bad\.alm, line 8"):
        load_yuma_almanac(bad)
    bad.write_text("")
    with pytest.raises(ValueError, match="bad.alm"):
        load_yuma_almanac(bad)

    badn = tmp_path / "bad.rnx"
    line = (DATA / "rinex3_sample.rnx").read_text().splitlines()[5]
    _corrupt(DATA / "rinex3_sample.rnx", badn, 6, line[:30] + "X" + line[31:])
    with pytest.raises(ValueError, match=r"bad\.rnx, line 6"):
        load_rinex_nav(badn)
    text = (DATA / "rinex3_sample.rnx").read_text().replace("END OF HEADER", "END OF HEADEX")
    badn.write_text(text)
    with pytest.raises(ValueError, match="END OF HEADER"):
        load_rinex_nav(badn)
    lines = (DATA / "rinex3_sample.rnx").read_text().splitlines()
    badn.write_text("\n".join(lines[:8]) + "\n")  # truncated first record
    with pytest.raises(ValueError, match=r"bad\.rnx, line 4"):
        load_rinex_nav(badn)
    with pytest.raises(ValueError, match="path"):
        load_rinex_nav(tmp_path / "missing.rnx")
