"""The broadcast-vs-IGS comparison's reference points, record selection and attitude, on the real
files of 2010-07-01 (tests/data/gnss), and where `skyfuse bench gnss` finds those files.

References: the control segment's antenna offsets come from NGA's table (not from these
files), the record choice from the nav file's own text, the Sun from almanac events and
pymap3d's sidereal time; nothing is compared with the code that produced it."""
from __future__ import annotations

import datetime as dt
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pymap3d
import pytest

from sitl.app.bench.gnss import DATA_FILES, checkout_data_dir, resolve_data_dir
from sitl.app.args import UsageError
from sitl.gnss import broadcast
from sitl.gnss.orbit_check import (GPS_BROADCAST_APC_M, GPS_SVN_BLOCK_2010, IGS05_PCO_M, check_orbits,
                                   nominal_yaw_axes, sun_position_ecef_m)
from sitl.gnss.rinex_clk import read_clk
from sitl.gnss.rinex_nav import read_nav
from sitl.gnss.sp3 import read_sp3

DATA = Path(__file__).resolve().parents[2] / "data" / "gnss"
REPO = Path(__file__).resolve().parents[3]
AU_M = 149_597_870_700.0
GPS_EPOCH = dt.datetime(1980, 1, 6)


def _gps_s(*ymdhms, leap_s=15.0):
    return (dt.datetime(*ymdhms) - GPS_EPOCH).total_seconds() + leap_s


@pytest.fixture(scope="module")
def files():
    return read_nav(DATA / "brdc1820.10n"), read_sp3(DATA / "igs15904.sp3"), read_clk(DATA / "igs15904.clk")


@pytest.fixture(scope="module")
def summary(files):
    return check_orbits(*files).summary


# --- the Sun and the nominal attitude ----------------------------------------------------------

def test_sun_at_the_2010_june_solstice_and_aphelion():
    # June solstice 2010-06-21 11:28 UTC: declination = obliquity 23.4385 deg, right ascension
    # 90 deg (of date; ~0.14 deg of precession since J2000 are not modelled), so the subsolar
    # longitude is 90 deg - GMST (pymap3d's sidereal time, an independent formula).
    when = dt.datetime(2010, 6, 21, 11, 28)
    s = sun_position_ecef_m(_gps_s(2010, 6, 21, 11, 28))
    dec = np.degrees(np.arcsin(s[2] / np.linalg.norm(s)))
    assert dec == pytest.approx(23.4385, abs=0.05)
    gmst_deg = np.degrees(pymap3d.datetime2sidereal(when, 0.0))
    lon = np.degrees(np.arctan2(s[1], s[0]))
    assert (lon - (90.0 - gmst_deg) + 180.0) % 360.0 - 180.0 == pytest.approx(0.0, abs=0.3)
    # aphelion 2010-07-06 11:30 UTC at 1.01670 AU
    r = np.linalg.norm(sun_position_ecef_m(_gps_s(2010, 7, 6, 11, 30)))
    assert r / AU_M == pytest.approx(1.01670, abs=5e-4)


def test_nominal_yaw_axes_are_a_right_handed_frame_with_x_to_the_sun():
    sp3 = read_sp3(DATA / "igs15904.sp3")
    r = sp3.pos_m[::7, :].reshape(-1, 3)
    t = np.repeat(sp3.t_gps_s[::7], sp3.pos_m.shape[1])
    ok = np.isfinite(r[:, 0])
    r, t = r[ok], t[ok]
    ex, ey, ez = nominal_yaw_axes(r, t)
    for a, b in ((ex, ey), (ey, ez), (ez, ex)):
        np.testing.assert_allclose(np.einsum("ij,ij->i", a, b), 0.0, atol=1e-12)
    np.testing.assert_allclose(np.cross(ex, ey), ez, atol=1e-12)
    np.testing.assert_allclose(np.einsum("ij,ij->i", ez, r) / np.linalg.norm(r, axis=1), -1.0, atol=1e-12)
    sun = sun_position_ecef_m(t) - r
    assert np.all(np.einsum("ij,ij->i", ex, sun) > 0)  # +x toward the Sun's side
    np.testing.assert_allclose(np.einsum("ij,ij->i", ey, sun) / np.linalg.norm(sun, axis=1), 0.0, atol=1e-12)


# --- which record is in force ------------------------------------------------------------------

def test_transmitted_record_is_the_one_a_receiver_holds():
    """PRN 5 on 2010-07-01 (values typed from brdc1820.10n): IODE 91 (Toe 10:00:00, ttm 08:46:00)
    and an upload IODE 26 (Toe 09:59:12, ttm 09:02:00). At 09:00 only IODE 91 has been
    transmitted, though IODE 26's Toe is nearer; at 09:15 IODE 26 is the latest transmitted."""
    g = read_nav(DATA / "brdc1820.10n").gps
    t = np.array([_gps_s(2010, 7, 1, 9, 0, leap_s=0.0), _gps_s(2010, 7, 1, 9, 15, leap_s=0.0)])
    sat = np.array(["G05", "G05"])
    tr = broadcast.select_transmitted(g, sat, t)
    near = g.select(sat, t)
    assert list(g.iode[tr]) == [91, 26]
    assert list(g.iode[near]) == [26, 26]
    st = broadcast.gps_states(g, sat, t, select="transmitted")
    assert list(st.record) == list(tr)
    with pytest.raises(ValueError, match="select"):
        broadcast.gps_states(g, sat, t, select="latest")


# --- reference points --------------------------------------------------------------------------

def test_every_block_is_radially_unbiased_at_the_control_segments_antenna_phase_centre(summary):
    """The broadcast orbit refers to the APC the control segment defines: at that point (NGA's
    offsets) the radial mean of every block vanishes (|mean| < 0.1 m against 0.1-1.6 m at the
    CoM or at igs05's APC), and the radial RMS falls to the ~0.2 m of the prediction error."""
    blocks = summary["by_block"]
    assert set(blocks) == {"BLOCK IIA", "BLOCK IIR-A", "BLOCK IIR-B", "BLOCK IIR-M"}
    for name, b in blocks.items():
        assert abs(b["radial_mean_m"]) < 0.1, name
        assert b["radial_rms_m"] < 0.3, name
    # at the CoM the radial means are minus the offsets: IIA -0.95, IIR-A -1.6, IIR-B/M ~0
    z_cs = {blk: np.mean([GPS_BROADCAST_APC_M[svn][2] for svn, bb in GPS_SVN_BLOCK_2010.values()
                          if bb == blk and svn in GPS_BROADCAST_APC_M]) for blk in blocks}
    for name, b in blocks.items():
        assert b["radial_mean_com_m"] == pytest.approx(-z_cs[name], abs=0.1), name
    assert blocks["BLOCK IIA"]["radial_mean_igs05_apc_m"] > 1.0  # igs05's APC is ~1.5 m lower
    rp = summary["reference_point"]
    assert rp["apc"] == "control-segment" and rp["offsets_for_the_date"]
    assert rp["control_segment_apc"]["radial_rms_m"] < 0.25
    assert rp["com"]["radial_rms_m"] > 0.9 and rp["igs05_apc"]["radial_rms_m"] > 0.9
    assert summary["radial_rms_m"] == rp["control_segment_apc"]["radial_rms_m"]


def test_the_sun_pointing_x_offset_sign_lowers_the_along_and_cross_errors(files):
    """Block IIA's x-offset (0.2794 m) along +x (toward the Sun) lowers along/cross RMS; along -x
    it would raise them: the attitude convention checked on the data."""
    nav, sp3, _ = files
    base = check_orbits(nav, sp3).summary
    flipped = dict(GPS_BROADCAST_APC_M)
    try:
        for svn, (x, y, z) in GPS_BROADCAST_APC_M.items():
            GPS_BROADCAST_APC_M[svn] = (-x, -y, z)
        neg = check_orbits(nav, sp3).summary
    finally:
        GPS_BROADCAST_APC_M.update(flipped)
    assert base["orbit_3d_rms_m"] < neg["orbit_3d_rms_m"]
    assert base["cross_rms_m"] < neg["cross_rms_m"]


def test_igs_clocks_moved_to_the_broadcast_apc_agree_better(summary):
    """The IGS clocks refer to igs05's APC; moved to the control segment's by (z_IGS - z_CS)/c
    they agree better with the broadcast clocks: an orbit-free check of the same offsets."""
    assert summary["clock_rms_ns"] < summary["clock_rms_ns_igs_clock_as_is"]
    assert summary["clock_rms_ns"] <= 10.0
    iia = summary["by_block"]["BLOCK IIA"]
    assert abs(iia["clock_mean_ns"]) < abs(iia["clock_mean_igs_as_is_ns"])


def test_gps_orbit_targets(summary):
    assert summary["orbit_3d_rms_m"] <= 2.0
    assert summary["reference_point"]["com"]["orbit_3d_rms_m"] <= 2.0
    assert summary["record_selection"]["gps"] == "transmitted"
    assert summary["record_selection"]["orbit_3d_rms_m_nearest"] <= 2.0
    assert summary["sisre_m"] < 1.0
    assert set(IGS05_PCO_M) >= {svn for svn, _ in GPS_SVN_BLOCK_2010.values()}


@pytest.mark.xfail(strict=True, reason="target 1.5 m once the reference points agree is NOT met: 1.54 m; "
                   "the rest is along-track prediction error (Block IIA 1.9 m RMS, one upload a day)")
def test_gps_orbit_within_1_5_m_once_the_reference_points_agree(summary):
    assert summary["orbit_3d_rms_m"] <= 1.5


# --- the bench's data folder -------------------------------------------------------------------

def test_bench_finds_the_checkout_data_and_refuses_without(tmp_path, monkeypatch):
    monkeypatch.chdir(REPO)  # run from the clone (the package may be installed from it, as CI's is)
    assert checkout_data_dir() == DATA
    assert resolve_data_dir(None) == DATA
    assert resolve_data_dir(tmp_path) == tmp_path  # given: used as is (argparse checks its files)
    fake = tmp_path / "site-packages" / "sitl" / "app" / "bench" / "gnss.py"  # an installed layout
    assert checkout_data_dir(fake) == DATA  # found through the current directory
    monkeypatch.chdir(tmp_path)  # elsewhere: neither the package's checkout nor the directory
    assert checkout_data_dir(fake) is None
    with pytest.raises(UsageError, match="--data DIR"):
        resolve_data_dir(None, fake)


def test_bench_in_an_installed_layout_is_a_one_line_usage_error(tmp_path):
    """The packages copied without tests/ (as pip installs them): `bench gnss` without --data
    exits 2 with one line naming --data; with --data it runs."""
    site = tmp_path / "site"
    for pkg in ("sitl", "filters", "vehicles", "ground_station"):
        shutil.copytree(REPO / pkg, site / pkg, ignore=shutil.ignore_patterns("__pycache__"))
    env = dict(os.environ, PYTHONPATH=str(site))
    cmd = [sys.executable, "-m", "sitl.app", "bench", "gnss", "--rounds", "1"]
    p = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert p.returncode == 2, p.stderr
    assert p.stderr.count("\n") == 1 and "--data DIR" in p.stderr and "Traceback" not in p.stderr
    data = tmp_path / "data"
    data.mkdir()
    for f in DATA_FILES:
        shutil.copy(DATA / f, data / f)
    p = subprocess.run(cmd + ["--data", str(data), "--json", str(tmp_path / "b.json")], cwd=tmp_path, env=env,
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    assert (tmp_path / "b.json").stat().st_size > 0


def test_cli_reference_point_and_record_flags(tmp_path, capsys):
    import json

    from sitl.app.cli import main

    out = tmp_path / "o"
    rc = main(["gnss", "orbits", "--nav", str(DATA / "brdc1820.10n"), "--sp3", str(DATA / "igs15904.sp3"),
               "--clk", str(DATA / "igs15904.clk"), "--apc", "igs05", "--gps-record", "nearest", "--by-satellite",
               "--out", str(out)])
    assert rc == 0
    res = json.loads((out / "result.json").read_text())
    assert res["reference_point"]["apc"] == "igs05" and res["record_selection"]["gps"] == "nearest"
    assert res["reference_point"]["precise"]["orbits"] == "centre of mass"
    assert "igs05" in res["reference_point"]["precise"]["clocks"]
    for key in ("orbit_3d_rms_m", "radial_rms_m", "along_rms_m", "cross_rms_m", "clock_rms_ns", "sisre_m",
                "by_satellite", "by_block"):
        assert key in res
    printed = capsys.readouterr().out
    assert "BLOCK IIR-A" in printed and "G09  G039  BLOCK IIA" in printed
    rc = main(["gnss", "orbits", "--nav", str(DATA / "brdc1820.10n"), "--sp3", str(DATA / "igs15904.sp3"),
               "--apc", "cs", "--out", str(out)])
    assert rc == 2 and "--apc" in capsys.readouterr().err


def test_helmert_fit_recovers_a_known_transformation_and_is_only_reported(summary):
    from sitl.gnss.orbit_check import helmert_fit

    rng = np.random.default_rng(7)
    r = rng.normal(size=(200, 3)) * 2.0e7
    w = np.array([1.0, -2.0, 3.0]) / (180.0 / np.pi * 3600e3)  # mas -> rad
    d = np.array([0.1, -0.2, 0.3]) + np.cross(w, r) + 2e-9 * r
    fit = helmert_fit(r, d)
    np.testing.assert_allclose(fit["translation_m"], [0.1, -0.2, 0.3], atol=1e-6)
    np.testing.assert_allclose(fit["rotation_mas"], [1.0, -2.0, 3.0], atol=1e-6)
    assert fit["scale_ppb"] == pytest.approx(2.0, abs=1e-6) and fit["orbit_3d_rms_m_after"] < 1e-6
    # on the day: a fit explains part of the along-track error, but the headline is not fitted
    h = summary["helmert_fit"]
    assert h["orbit_3d_rms_m_after"] < summary["orbit_3d_rms_m"]
