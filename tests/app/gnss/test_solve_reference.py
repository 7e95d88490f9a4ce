"""The references of `skyfuse gnss solve` on station 0759 (tests/data/gnss), each checked against
something computed independently here:

* the dual-frequency slant ionosphere (solve_reference.dual_frequency_slant) against the same
  geometry-free combination computed in this file from georinex's reading of the file and of the
  navigation file's TGD (arcs split by this file's own loop);
* the zenith / receiver-bias least squares against an exactly known synthetic case;
* the data path (broadcast orbit, clock, TGD, light time, Sagnac: solve_data.prepare) against
  RTKLIB's own L1 single-point solution epoch by epoch, with the same Klobuchar and a standard-
  atmosphere Saastamoinen troposphere applied in a plain least-squares fix written here.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from sitl.app.gnss.solve_data import least_squares_fix, prepare
from sitl.app.gnss.solve_reference import dual_frequency_slant, rnx2rtkp_path, run_rtklib, zenith_and_bias
from sitl.geodesy import ecef_to_aer, ecef_to_enu, ecef_to_geodetic
from sitl.gnss.klobuchar import klobuchar_delay_m
from sitl.gnss.rinex_nav import read_nav
from sitl.gnss.rinex_obs import read_obs

DATA = Path(__file__).resolve().parents[2] / "data" / "gnss"
OBS, NAV = DATA / "07590920.05o", DATA / "07590920.05n"
C = 299_792_458.0
F1, F2 = 1575.42e6, 1227.60e6
APPROX = np.array([-3976219.5082, 3382372.5671, 3652512.9849])  # typed from the header


@pytest.fixture(scope="module")
def ep():
    return prepare(read_obs(OBS), read_nav(NAV))


def test_dual_frequency_slant_against_georinex(ep):
    georinex = pytest.importorskip("georinex")
    o = georinex.load(str(OBS), useindicators=True)
    nav = georinex.load(str(NAV))
    sats = list(o.sv.values)
    assert tuple(sats) == ep.sats
    c1, p2 = o["C1"].values, o["P2"].values
    l1, l2 = o["L1"].values, o["L2"].values
    lli = (np.nan_to_num(o["L1lli"].values).astype(int) | np.nan_to_num(o["L2lli"].values).astype(int)) & 1
    # the TGD of the record nearest in time (its Toc), per epoch: it changes with the record
    t_obs = o.time.values
    tgd = np.full(c1.shape, np.nan)
    for j, s in enumerate(sats):
        rec = nav.sel(sv=s)
        ok = np.isfinite(rec["TGD"].values)
        toc, v = rec.time.values[ok], rec["TGD"].values[ok]
        near = np.argmin(np.abs((t_obs[:, None] - toc[None, :]).astype("timedelta64[s]").astype(float)), axis=1)
        tgd[:, j] = v[near]
    gamma = (F1 / F2) ** 2
    lam1, lam2 = C / F1, C / F2
    T, S = c1.shape
    want = np.full((T, S), np.nan)
    for j, s in enumerate(sats):
        icode = (p2[:, j] - c1[:, j]) / (gamma - 1.0) - C * tgd[:, j]
        gf = l1[:, j] * lam1 - l2[:, j] * lam2
        iphase = gf / (gamma - 1.0)  # the phase advances: L_i = rho - I_i (+ ambiguity), I_2 = gamma I_1
        ok = np.isfinite(icode) & np.isfinite(iphase)
        start = None
        for k in range(T + 1):
            brk = k == T or not ok[k] or lli[k, j] or (start is not None and abs(gf[k] - gf[k - 1]) > 0.5)
            if brk and start is not None:
                arc = slice(start, k)
                want[arc, j] = iphase[arc] + np.mean(icode[arc] - iphase[arc])
                start = None
            if k < T and ok[k] and start is None:
                start = k
    use = np.ones((T, S), dtype=bool)
    got, arcs = dual_frequency_slant(ep.c1_m, ep.p2_m, ep.l1_cyc, ep.l2_cyc, ep.lli, np.nan_to_num(ep.tgd_s), use)
    assert np.array_equal(np.isfinite(got), np.isfinite(want))
    np.testing.assert_allclose(got[np.isfinite(got)], want[np.isfinite(want)], atol=1e-6)
    assert arcs.max() + 1 >= S - 2  # one arc or more per satellite (some break at an LLI flag)
    # physically: a levelled slant L1 delay before the receiver bias is metres, not tens
    assert np.nanmax(np.abs(got)) < 20.0
    # the sign of the phase term: the levelled series follows the code's own geometry-free
    # series (both grow with the TEC), leaving only code noise and multipath; with the sign
    # flipped the leftover would exceed the code series' own spread about its mean
    icode = (p2 - c1) / (gamma - 1.0) - C * tgd
    for j in range(S):
        m = np.isfinite(got[:, j]) & np.isfinite(icode[:, j])
        if m.sum() < 40:
            continue
        left = np.std(icode[m, j] - got[m, j])
        spread = np.std(icode[m, j])
        assert left < spread, sats[j]


def test_zenith_and_bias_recovers_an_exact_case():
    rng = np.random.default_rng(3)
    T, S = 40, 7
    m = rng.uniform(1.0, 3.0, (T, S))
    iz = 2.0 + np.sin(np.arange(T) / 7.0)
    b = -4.25
    slant = m * iz[:, None] + b
    slant[rng.random((T, S)) < 0.2] = np.nan
    got_iz, got_b, resid = zenith_and_bias(slant, m)
    assert got_b == pytest.approx(b, abs=1e-9)
    np.testing.assert_allclose(got_iz, iz, atol=1e-9)
    assert resid < 1e-9


def _saastamoinen_m(lat, h, el, humidity=0.7):
    """Saastamoinen with a standard atmosphere (1013.25 hPa at sea level, 15 C, lapse 6.5 K/km)."""
    p = 1013.25 * (1.0 - 2.2557e-5 * h) ** 5.2568
    tk = 15.0 - 6.5e-3 * h + 273.16
    e = 6.108 * humidity * np.exp((17.15 * tk - 4684.0) / (tk - 38.45))
    cz = np.cos(np.pi / 2 - el)
    dry = 0.0022768 * p / (1.0 - 0.00266 * np.cos(2.0 * lat) - 0.00028 * h / 1e3) / cz
    return dry + 0.002277 * (1255.0 / tk + 0.05) * e / cz


@pytest.mark.skipif(rnx2rtkp_path() is None, reason="rnx2rtkp not installed (Debian package rtklib)")
def test_data_path_agrees_with_rtklib_epoch_by_epoch(ep):
    nav = read_nav(NAV)
    t_rtk, xyz = run_rtklib(OBS, NAV, el_mask_deg=10.0)
    np.testing.assert_allclose(t_rtk, ep.t_gps_s, atol=1e-3)
    T = ep.t_gps_s.size
    x = np.concatenate([np.broadcast_to(APPROX, (T, 3)), np.zeros((T, 1))], axis=1)
    for _ in range(3):
        az, el, _ = ecef_to_aer(x[:, None, :3], ep.sat_pos_m)
        lat, lon, h = ecef_to_geodetic(x[:, :3])
        use = np.isfinite(ep.pr_m) & (np.nan_to_num(el, nan=-1.0) >= math.radians(10.0))
        iono = klobuchar_delay_m(nav.ion_alpha, nav.ion_beta, lat[:, None], lon[:, None], np.nan_to_num(az),
                                 np.nan_to_num(el), ep.t_gps_s[:, None])
        pr = ep.pr_m - iono - _saastamoinen_m(lat[:, None], h[:, None], el)
        pos, clk, _ = least_squares_fix(np.where(use, pr, 0.0), np.nan_to_num(ep.sat_pos_m), use, x0=x)
        x = np.concatenate([pos, clk[:, None]], axis=1)
    d = pos - xyz
    # RTKLIB weights by elevation and this fix does not: decimetres apart, never metres. A missing
    # Sagnac term would be ~20 m east, a missing TGD metres, a light-time error tens of metres.
    assert np.all(np.sqrt(np.mean(d * d, axis=0)) < 0.35)
    assert np.max(np.abs(d)) < 1.0
    lat0, lon0, h0 = ecef_to_geodetic(APPROX)
    rms = lambda p: float(np.sqrt(np.mean(np.sum(ecef_to_enu(p, lat0, lon0, h0) ** 2, axis=1))))  # noqa: E731
    assert rms(xyz) == pytest.approx(1.21, abs=0.01)  # the RTKLIB figure
    assert rms(pos) < 1.6
