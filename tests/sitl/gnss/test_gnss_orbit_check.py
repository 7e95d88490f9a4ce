"""Broadcast orbits and clocks against the IGS products of the same day (the independent
reference), and `skyfuse gnss orbits` end to end, bad input included."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from sitl.app.cli import main
from sitl.gnss import broadcast
from sitl.gnss.orbit_check import check_orbits
from sitl.gnss.rinex_clk import read_clk
from sitl.gnss.rinex_nav import read_nav
from sitl.gnss.sp3 import read_sp3

DATA = Path(__file__).resolve().parents[2] / "data" / "gnss"
C = 299_792_458.0


@pytest.fixture(scope="module")
def gps():
    return check_orbits(read_nav(DATA / "brdc1820.10n"), read_sp3(DATA / "igs15904.sp3"),
                        read_clk(DATA / "igs15904.clk")).summary


@pytest.fixture(scope="module")
def glonass():
    return check_orbits(read_nav(DATA / "brdc0910.09g"), read_sp3(DATA / "igl15253.sp3")).summary


def test_gps_broadcast_against_igs_finals(gps):
    # IGS products table: broadcast orbits ~100 cm (1D mean RMS) -> ~1.7 m 3D; clocks ~5 ns
    assert gps["orbit_3d_rms_m"] <= 2.0
    assert gps["reference_point"]["uncorrected"]["orbit_3d_rms_m"] <= 2.0
    assert -1.0 < gps["reference_point"]["uncorrected"]["radial_mean_m"] < -0.5  # APC below the CoM
    # the clk file: 00:00-00:55, 12 epochs x 30 satellites, but PRN 9 at 00:00: the file's first
    # PRN 9 record (Toe 02:00) was transmitted at 00:00:18 (ttm 345618), the one before is not in it
    assert gps["clock_rms_ns"] <= 10.0 and gps["clock_samples"] == 359
    assert gps["no_record_in_force"] == 1 and gps["by_satellite"]["G09"]["no_record_in_force"] == 1
    assert gps["clock_rms_ns_sp3_day"] <= 10.0
    assert gps["sisre_m"] < 2.0
    # PRN 1 (SVN49) is flagged unhealthy (63) in every record but the mislabelled copy of PRN 23
    assert gps["by_satellite"]["G01"]["epochs"] == 0 and gps["by_satellite"]["G01"]["unhealthy_excluded"] == 96
    assert gps["mislabelled_records"] == 1
    assert gps["satellites_compared"] == 30  # G25 (SVN62, the first IIF) is unhealthy all day
    assert gps["unhealthy_excluded"] == 192


def test_glonass_broadcast_against_igs_finals(glonass):
    assert glonass["orbit_3d_rms_m"] <= 10.0
    assert glonass["satellites_compared"] == 18
    assert glonass["clock_note"] is not None  # igl15253.sp3's clocks are the broadcast ones


def test_glonass_pz90_02_shift_brings_the_orbits_closer():
    nav, sp3 = read_nav(DATA / "brdc0910.09g"), read_sp3(DATA / "igl15253.sp3")
    T, S = sp3.pos_m.shape[:2]
    sat, t = np.tile(np.array(sp3.sats), T), np.repeat(sp3.t_gps_s, S)
    ref = sp3.pos_m.reshape(-1, 3)
    itrf = broadcast.glonass_states(nav.glonass, sat, t, itrf=True)
    pz = broadcast.glonass_states(nav.glonass, sat, t, itrf=False)
    m = itrf.healthy & np.isfinite(ref[:, 0])
    d_itrf = np.mean(itrf.pos_m[m] - ref[m], axis=0)
    d_pz = np.mean(pz.pos_m[m] - ref[m], axis=0)
    assert np.linalg.norm(d_itrf) < np.linalg.norm(d_pz)
    np.testing.assert_allclose(itrf.pos_m[m] - pz.pos_m[m], np.broadcast_to([-0.36, 0.08, 0.18], (m.sum(), 3)))


def test_glonass_rk4_against_scipy_dop853():
    r = read_nav(DATA / "brdc0910.09g").glonass
    k = np.arange(0, len(r), 50)
    dt = np.where(k % 100 == 0, 900.0, -1500.0)
    p, v = broadcast.glonass_integrate(r.pos_m[k], r.vel_m_s[k], r.acc_m_s2[k], dt)
    for j, kk in enumerate(k):
        def f(_, y, a=r.acc_m_s2[kk]):
            return broadcast._glo_deriv(y[None, :], a[None, :])[0]

        sol = solve_ivp(f, (0.0, dt[j]), np.r_[r.pos_m[kk], r.vel_m_s[kk]], method="DOP853", rtol=1e-12, atol=1e-6)
        assert np.abs(sol.y[:3, -1] - p[j]).max() < 0.01  # RK4 with 60 s steps: < 1 cm


def test_gps_relativistic_term_equals_minus_2_r_dot_v_over_c2():
    g = read_nav(DATA / "brdc1820.10n").gps
    t0 = float(g.toe_gps_s[0])
    sats = np.array(g.sats * 3)
    t = np.repeat([t0, t0 + 1800.0, t0 + 5400.0], len(g.sats))
    st = broadcast.gps_states(g, sats, t)
    m = st.ok
    rv = np.einsum("ij,ij->i", st.pos_m[m], st.vel_m_s[m])  # r.v is the same in ECEF and ECI
    # equal on a Keplerian orbit; the harmonic terms and J2 make them differ by < 0.1 ns (3 cm)
    np.testing.assert_allclose(st.relativistic_s[m], -2.0 * rv / C**2, rtol=0, atol=1e-10)
    assert np.abs(st.relativistic_s[m]).max() > 2e-8  # the term itself is tens of ns
    np.testing.assert_allclose(st.clock_l1_s[m], st.clock_s[m] - g.tgd_s[st.record[m]])


def test_cli_writes_result_and_plot(tmp_path, capsys):
    out = tmp_path / "o"
    rc = main(["gnss", "orbits", "--nav", str(DATA / "brdc1820.10n"), "--sp3", str(DATA / "igs15904.sp3"),
               "--clk", str(DATA / "igs15904.clk"), "--out", str(out)])
    assert rc == 0
    res = json.loads((out / "result.json").read_text())
    for key in ("orbit_3d_rms_m", "radial_rms_m", "along_rms_m", "cross_rms_m", "clock_rms_ns", "sisre_m",
                "by_satellite", "unhealthy_excluded", "reference_point"):
        assert key in res
    assert (out / "orbit_errors.png").stat().st_size > 10_000
    assert "orbit 3D RMS" in capsys.readouterr().out


def _one_line_error(capsys, argv):
    rc = main(argv)
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and "Traceback" not in err
    return err


def test_cli_bad_input_is_one_line_naming_file_and_line(tmp_path, capsys):
    sp3, nav = str(DATA / "igs15904.sp3"), str(DATA / "brdc1820.10n")
    lines = (DATA / "igs15904.sp3").read_text().splitlines()
    (tmp_path / "t.sp3").write_text("\n".join(lines[:500]) + "\n")
    err = _one_line_error(capsys, ["gnss", "orbits", "--nav", nav, "--sp3", str(tmp_path / "t.sp3"), "--out", str(tmp_path)])
    assert "t.sp3, line 500: header announces 96 epochs" in err
    nl = (DATA / "brdc1820.10n").read_text().splitlines()
    nl[20] = nl[20][:30] + "#" + nl[20][31:]
    (tmp_path / "g.10n").write_text("\n".join(nl) + "\n")
    err = _one_line_error(capsys, ["gnss", "orbits", "--nav", str(tmp_path / "g.10n"), "--sp3", sp3, "--out", str(tmp_path)])
    assert "g.10n, line 21: cannot read a number" in err
    (tmp_path / "v.10n").write_text("     5.00" + (DATA / "brdc1820.10n").read_text()[9:])
    err = _one_line_error(capsys, ["gnss", "orbits", "--nav", str(tmp_path / "v.10n"), "--sp3", sp3, "--out", str(tmp_path)])
    assert "v.10n, line 1: unsupported RINEX version 5" in err
    # GLONASS broadcast against GPS precise orbits: no satellite to compare
    err = _one_line_error(capsys, ["gnss", "orbits", "--nav", str(DATA / "brdc0910.09g"), "--sp3", sp3, "--out", str(tmp_path)])
    assert "igs15904.sp3: no satellite of the navigation file's systems" in err
    # a nav file of another day: no record in force at any epoch
    err = _one_line_error(capsys, ["gnss", "orbits", "--nav", str(DATA / "07590920.05n"), "--sp3", sp3, "--out", str(tmp_path)])
    assert "07590920.05n: no healthy broadcast record in force" in err
    err = _one_line_error(capsys, ["gnss", "orbits", "--nav", str(tmp_path / "missing.10n"), "--sp3", sp3, "--out", str(tmp_path)])
    assert "missing.10n" in err


@pytest.mark.parametrize("words", [["gnss"], ["gnss", "orbits"]])
def test_gnss_help(words, capsys):
    from sitl.app.cli import build_parser

    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args(words + ["--help"])
    assert exc.value.code == 0 and "usage:" in capsys.readouterr().out


def test_gnss_bench_runs(tmp_path, capsys):
    rc = main(["bench", "gnss", "--data", str(DATA), "--rounds", "1", "--json", str(tmp_path / "b.json")])
    assert rc == 0
    res = json.loads((tmp_path / "b.json").read_text())
    assert {"read_obs_1h_s", "orbit_check_gps_day_s", "orbit_check_glonass_day_s"} <= set(res)  # no timing asserts
