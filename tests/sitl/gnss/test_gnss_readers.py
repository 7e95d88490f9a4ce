"""The RINEX/SP3/clock readers against values typed from the files' own text, and against
georinex 1.16.2 (an independent reader) on the same files."""
from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

from sitl.gnss.rinex_clk import read_clk
from sitl.gnss.rinex_common import GnssFileError, calendar_seconds
from sitl.gnss.rinex_nav import read_nav
from sitl.gnss.rinex_obs import read_obs
from sitl.gnss.sp3 import read_sp3

DATA = Path(__file__).resolve().parents[2] / "data" / "gnss"
WEEK = 604800.0
T_2010_07_01 = 1590 * WEEK + 4 * 86400.0  # GPS week 1590, day 4 (## line of igs15904.sp3: 345600 s)


def _georinex():
    gr = pytest.importorskip("georinex")
    warnings.simplefilter("ignore")
    return gr


# --- navigation ------------------------------------------------------------------------------

def test_gps_nav_first_and_duplicate_records_typed_from_the_text():
    nav = read_nav(DATA / "brdc1820.10n")
    assert nav.version == 2.0 and nav.leap_seconds == 15
    assert nav.ion_alpha == (0.4657e-08, 0.1490e-07, -0.5960e-07, -0.1192e-06)  # header line 4
    assert nav.ion_beta == (0.8192e05, 0.8192e05, -0.6554e05, -0.5243e06)
    g = nav.gps
    assert len(g) == 421 and nav.glonass is None  # every record, none dropped
    # lines 9-16: ' 1 10  7  1  0  0  0.0-0.136290676892D-03-0.397903932026D-11 0.0...'
    assert g.sat[0] == "G01" and g.line[0] == 9
    assert g.toc_gps_s[0] == T_2010_07_01
    assert g.af0_s[0] == -0.136290676892e-03 and g.af1[0] == -0.397903932026e-11
    assert g.iode[0] == 63.0 and g.crs_m[0] == -0.897500000000e02 and g.delta_n_rad_s[0] == 0.468055210664e-08
    assert g.m0_rad[0] == -0.307674634178e01 and g.cuc_rad[0] == -0.476092100143e-05
    assert g.e[0] == 0.483528291807e-02 and g.cus_rad[0] == 0.545941293240e-05 and g.sqrt_a[0] == 0.515480139732e04
    assert g.toe_gps_s[0] == 1590 * WEEK + 345600.0 and g.cic_rad[0] == 0.558793544769e-08
    assert g.omega0_rad[0] == 0.292603518708e01 and g.i0_rad[0] == 0.965451250348e00
    assert g.omega_dot_rad_s[0] == -0.813998192006e-08 and g.idot_rad_s[0] == -0.171792870148e-09
    assert g.week[0] == 1590 and g.health[0] == 63 and g.fit_h[0] == 4.0  # fit 0 -> 4 h (IS-GPS-200)
    # PRN 1's record of line 937 (06:00, health 0) repeats PRN 23's of line 1089 word for word
    k1 = int(np.flatnonzero(g.line == 937)[0])
    k23 = int(np.flatnonzero(g.line == 1089)[0])
    assert g.sat[k1] == "G01" and g.sat[k23] == "G23" and g.health[k1] == 0
    assert g.af0_s[k1] == g.af0_s[k23] == 0.364852137864e-03 and g.iode[k1] == 90.0 and g.fit_h[k1] == 4.0
    assert g.ttm_s[k1] == 0.362640e06 and g.ttm_s[k23] == 0.360000e06
    assert list(np.flatnonzero(g.mislabelled())) == [k1]  # the copy, not PRN 23's own record


def test_glonass_nav_first_record_typed_from_the_text():
    nav = read_nav(DATA / "brdc0910.09g")
    r = nav.glonass
    assert nav.version == 2.01 and nav.gps is None and len(r) == 912
    # line 8: ' 2 09  4  1  0 15  0.0 0.206762924790E-04-0.272848410532E-11 0.900000000000E+03'
    assert r.sat[0] == "R02" and r.line[0] == 8
    assert r.toc_gps_s[0] == calendar_seconds(2009, 4, 1, 0, 15, 0.0) + 15  # UTC + LEAP SECONDS 15
    assert r.tau_n_s[0] == -0.206762924790e-04 and r.gamma_n[0] == -0.272848410532e-11 and r.tk_s[0] == 900.0
    np.testing.assert_array_equal(r.pos_m[0], [0.936473925781e07, -0.159087973633e08, -0.176143896484e08])
    np.testing.assert_allclose(r.vel_m_s[0], [-0.267867088318e03, 0.239853191376e04, -0.230765628815e04], rtol=1e-15)
    np.testing.assert_allclose(r.acc_m_s2[0], [0.0, 0.186264514923e-05, 0.186264514923e-05], rtol=1e-15)
    assert r.health[0] == 0 and r.freq_num[0] == 1 and r.age_days[0] == 0.0


@pytest.mark.parametrize("name", ["brdc1820.10n", "07590920.05n"])
def test_gps_nav_against_georinex(name):
    gr = _georinex()
    g = read_nav(DATA / name).gps
    ds = gr.load(DATA / name)
    pairs = {"sqrtA": g.sqrt_a, "Eccentricity": g.e, "M0": g.m0_rad, "Toe": g.toe_gps_s % WEEK, "Crs": g.crs_m,
             "Cis": g.cis_rad, "SVclockBias": g.af0_s, "TGD": g.tgd_s, "health": g.health, "IODE": g.iode}
    toc = np.array(ds.time.values, dtype="datetime64[ns]")
    t_gr = (toc - np.datetime64("1980-01-06T00:00:00")).astype("timedelta64[ns]").astype(float) / 1e9
    checked = 0
    keys = list(zip(g.sat.tolist(), g.toc_gps_s.tolist()))
    for k in range(len(g)):
        if keys.count(keys[k]) > 1:
            continue  # two records with the same (sv, toc): georinex's grid keeps one of them
        i = int(np.flatnonzero(np.isclose(t_gr, g.toc_gps_s[k], atol=1e-3, rtol=0))[0])
        row = ds.sel(sv=g.sat[k]).isel(time=i)
        for key, ours in pairs.items():
            assert float(row[key]) == pytest.approx(float(ours[k]), rel=1e-12, abs=1e-300), (key, k)
        checked += 1
    assert checked >= 0.9 * len(g)


def test_glonass_nav_against_georinex():
    gr = _georinex()
    r = read_nav(DATA / "brdc0910.09g").glonass
    ds = gr.load(DATA / "brdc0910.09g")
    t_gr = (np.array(ds.time.values, dtype="datetime64[ns]") - np.datetime64("1980-01-06")).astype(float) / 1e9
    for k in range(0, len(r), 37):
        # georinex keeps the file's UTC epochs: ours are GPS = UTC + 15 s
        i = int(np.flatnonzero(np.isclose(t_gr + 15, r.toc_gps_s[k], atol=1e-3, rtol=0))[0])
        row = ds.sel(sv=r.sat[k]).isel(time=i)
        assert float(row["X"]) * (1.0 if float(abs(row["X"])) > 1e6 else 1e3) == pytest.approx(r.pos_m[k, 0], rel=1e-12)
        assert float(row["SVclockBias"]) == pytest.approx(-r.tau_n_s[k], rel=1e-12)
        assert int(row["FreqNum"]) == r.freq_num[k]


def test_rinex3_mixed_nav_and_select_by_toe(tmp_path):
    nav = read_nav(DATA.parent / "rinex3_sample.rnx")  # the 2025 sample used by test_orbits
    assert nav.version == 3.04 and len(nav.gps) == 4
    g = read_nav(DATA / "brdc1820.10n").gps
    # G05's records: toe at 0, 2, 4, ... h; at 01:10 the 02:00 record is nearest and in force
    i = g.select(["G05", "G05", "G05", "G99"], T_2010_07_01 + np.array([0.0, 4200.0, 86400.0 + 8000.0, 0.0]))
    assert g.toe_gps_s[i[0]] == T_2010_07_01 and g.toe_gps_s[i[1]] == T_2010_07_01 + 7200.0
    assert i[2] == -1 and i[3] == -1  # beyond every fit interval / unknown satellite


# --- SP3 and clocks --------------------------------------------------------------------------

def test_sp3_typed_from_the_text():
    o = read_sp3(DATA / "igs15904.sp3")
    assert o.version == "c" and o.coord_sys == "IGS05" and o.agency == "IGS" and o.time_system == "GPS"
    assert len(o.sats) == 32 and o.t_gps_s.size == 96 and o.interval_s == 900.0
    assert o.t_gps_s[0] == T_2010_07_01 and o.t_gps_s[1] - o.t_gps_s[0] == 900.0
    # 'PG02 -14889.160729  -5131.952946 -21416.801336    269.108429'
    np.testing.assert_allclose(o.pos_m[0, o.index("G02")], [-14889160.729, -5131952.946, -21416801.336], rtol=1e-15)
    assert o.clock_s[0, o.index("G02")] == pytest.approx(269.108429e-6, rel=1e-14)
    assert np.isnan(o.clock_s[0, o.index("G01")])  # 999999.999999: no value
    # 'PG32  24669.573362  -7422.063705  -5325.411899    -28.330453' at the last epoch
    np.testing.assert_allclose(o.pos_m[-1, o.index("G32")], [24669573.362, -7422063.705, -5325411.899], rtol=1e-15)
    r = read_sp3(DATA / "igl15253.sp3")
    assert r.sats[:3] == ("R02", "R03", "R04") and len(r.sats) == 18
    np.testing.assert_allclose(r.pos_m[0, 0], [9675793.281, -17954197.593, -15333306.358], rtol=1e-15)


@pytest.mark.parametrize("name", ["igs15904.sp3", "igl15253.sp3"])
def test_sp3_against_georinex(name):
    gr = _georinex()
    o = read_sp3(DATA / name)
    ds = gr.load_sp3(DATA / name, None)
    pos = ds["position"].sel(sv=list(o.sats)).values * 1e3  # km
    assert pos.shape == o.pos_m.shape
    ok = np.isfinite(o.pos_m)
    np.testing.assert_allclose(o.pos_m[ok], pos[ok], rtol=0, atol=1e-6)
    clk = ds["clock"].sel(sv=list(o.sats)).values * 1e-6
    okc = np.isfinite(o.clock_s) & np.isfinite(clk)
    np.testing.assert_allclose(o.clock_s[okc], clk[okc], rtol=1e-12, atol=0)


def test_clock_file_typed_from_the_text():
    c = read_clk(DATA / "igs15904.clk")
    assert c.version == 3.0 and c.t_gps_s.size == 12 and c.t_gps_s[0] == T_2010_07_01
    assert c.t_gps_s[-1] - c.t_gps_s[0] == 55 * 60.0  # the file holds 00:00-00:55 only
    assert "G01" not in c.sats and len(c.sats) == 30
    # 'AS G02  2010 07 01 00 00  0.000000  2    2.691084288582e-04  1.507490528240e-11'
    assert c.bias_s[0, c.sats.index("G02")] == 2.691084288582e-04
    assert c.sigma_s[0, c.sats.index("G02")] == 1.507490528240e-11
    # 'AS G32  2010 07 01 00 55  0.000000  2   -2.762406435746e-05  2.791815849820e-11'
    assert c.bias_s[-1, c.sats.index("G32")] == -2.762406435746e-05
    # 'AR GPST 2010 07 01 00 00  0.000000  2   -2.214541847585e-09  0.0...'
    assert c.station_bias_s[0, c.stations.index("GPST")] == -2.214541847585e-09
    # the IGS final clock equals the SP3's clock column at a common epoch (independent files)
    o = read_sp3(DATA / "igs15904.sp3")
    assert c.bias_s[0, c.sats.index("G02")] == pytest.approx(o.clock_s[0, o.index("G02")], abs=1e-12)
    assert c.bias_at(["G02"], c.t_gps_s[0] + 150.0)[0] == pytest.approx(
        0.5 * (c.bias_s[0, c.sats.index("G02")] + c.bias_s[1, c.sats.index("G02")]), rel=1e-12)


# --- observations ----------------------------------------------------------------------------

def test_obs_typed_from_the_text():
    o = read_obs(DATA / "07590920.05o")
    assert o.version == 2.10 and o.marker == "0759" and o.receiver == "TRIMBLE 5700" and o.interval_s == 30.0
    np.testing.assert_array_equal(o.approx_position_m, [-3976219.5082, 3382372.5671, 3652512.9849])
    assert o.codes == {"G": ("L1", "C1", "L2", "P2")}
    assert o.t_gps_s.size == 120 and o.t_gps_s[0] == calendar_seconds(2005, 4, 2, 0, 0, 0.0)
    # ' 05  4  2  0  0  0.0000000  0  8G 3G 7G 8G11G19G20G24G28'
    seen = [s for s in o.sats if np.isfinite(o.get("C1", s)[0])]
    assert seen == ["G03", "G07", "G08", "G11", "G19", "G20", "G24", "G28"]
    # '  55923622.160    24767686.375    43647388.2424   24767684.8224'  (G03)
    assert o.get("L1", "G03")[0] == 55923622.160 and o.get("C1", "G03")[0] == 24767686.375
    assert o.get("L2", "G03")[0] == 43647388.242 and o.get("P2", "G03")[0] == 24767684.822
    assert o.lli["L2"][0, o.column("G03")] == 4 and o.lli["L1"][0, o.column("G03")] == 0  # 4: under AS
    # line 855-856: an event (flag 4, one comment line) is skipped; line 857's epoch is 00:48:00.004
    k = int(np.flatnonzero(np.isclose(o.t_gps_s - o.t_gps_s[0], 48 * 60 + 0.004, atol=1e-6))[0])
    assert o.get("L1", "G01")[k] == 1600872.379 and o.get("P2", "G01")[k] == 25881665.610


def test_obs_against_georinex():
    gr = _georinex()
    o = read_obs(DATA / "07590920.05o")
    ds = gr.load(DATA / "07590920.05o")
    for c in ("L1", "C1", "L2", "P2"):
        theirs = ds[c].sel(sv=list(o.sats)).values
        np.testing.assert_array_equal(np.isnan(theirs), np.isnan(o.data[c]))
        np.testing.assert_array_equal(theirs[~np.isnan(theirs)], o.data[c][~np.isnan(theirs)])


def test_rinex3_obs(tmp_path):
    p = tmp_path / "t.rnx"
    def f(v, lli=" ", ssi=" "):
        return f"{v:14.3f}{lli}{ssi}"

    p.write_text(
        "     3.04           OBSERVATION DATA    M                   RINEX VERSION / TYPE\n"
        "G    4 C1C L1C D1C S1C                                      SYS / # / OBS TYPES\n"
        "R    2 C1C L1C                                              SYS / # / OBS TYPES\n"
        "  1 R01  1                                                  GLONASS SLOT / FRQ #\n"
        "                                                            END OF HEADER\n"
        "> 2020 01 02 03 04  5.0000000  0  2\n"
        + "G05" + f(20000000.123, " ", "7") + f(105100000.123, "1", "5") + f(-1234.567) + f(45.0) + "\n"
        + "R01" + f(21000000.5) + f(112200000.25) + "\n")
    o = read_obs(p)
    assert o.codes == {"G": ("C1C", "L1C", "D1C", "S1C"), "R": ("C1C", "L1C")} and o.glonass_slots == {"R01": 1}
    assert o.t_gps_s[0] == calendar_seconds(2020, 1, 2, 3, 4, 5.0)
    assert o.get("C1C", "G05")[0] == 20000000.123 and o.ssi["C1C"][0, 0] == 7 and o.lli["C1C"][0, 0] == 0
    assert o.get("L1C", "G05")[0] == 105100000.123 and o.lli["L1C"][0, 0] == 1 and o.ssi["L1C"][0, 0] == 5
    assert o.get("D1C", "G05")[0] == -1234.567 and o.get("S1C", "G05")[0] == 45.0
    assert o.get("L1C", "R01")[0] == 112200000.250 and np.isnan(o.data["D1C"][0, o.column("R01")])


# --- bad files: one message naming the file and line ------------------------------------------

def _write_lines(src, dst, edit):
    lines = Path(src).read_text().splitlines()
    edit(lines)
    Path(dst).write_text("\n".join(lines) + "\n")
    return dst


def test_bad_files_name_the_file_and_line(tmp_path):
    def garble(lines):
        lines[99] = lines[99][:25] + "XYZ" + lines[99][28:]

    with pytest.raises(GnssFileError, match=r"n\.10n, line 100: cannot read a number"):
        read_nav(_write_lines(DATA / "brdc1820.10n", tmp_path / "n.10n", garble))
    with pytest.raises(GnssFileError, match=r"t\.10n, line 201: record truncated"):
        read_nav(_write_lines(DATA / "brdc1820.10n", tmp_path / "t.10n", lambda ls: ls.__delitem__(slice(201, None))))
    with pytest.raises(GnssFileError, match=r"v\.10n, line 1: unsupported RINEX version 4"):
        read_nav(_write_lines(DATA / "brdc1820.10n", tmp_path / "v.10n",
                              lambda ls: ls.__setitem__(0, "     4.00" + ls[0][9:])))
    with pytest.raises(GnssFileError, match=r"s\.sp3, line \d+: header announces 96 epochs, the file has 48"):
        read_sp3(_write_lines(DATA / "igs15904.sp3", tmp_path / "s.sp3",
                              lambda ls: ls.__delitem__(slice(22 + 48 * 33, None))))
    with pytest.raises(GnssFileError, match=r"g\.sp3, line 25: cannot read a number"):
        read_sp3(_write_lines(DATA / "igs15904.sp3", tmp_path / "g.sp3",
                              lambda ls: ls.__setitem__(24, ls[24][:10] + "ABC" + ls[24][13:])))
    with pytest.raises(GnssFileError, match=r"a\.sp3, line 1: unsupported SP3 version 'a'"):
        read_sp3(_write_lines(DATA / "igs15904.sp3", tmp_path / "a.sp3",
                              lambda ls: ls.__setitem__(0, "#a" + ls[0][2:])))
    # line 857: ' 05  4  2  0 48  0.0040000  0  8G 1G 4G ...' and its 8 observation lines
    with pytest.raises(GnssFileError, match=r"o\.05o, line 863: epoch of line 857 truncated"):
        read_obs(_write_lines(DATA / "07590920.05o", tmp_path / "o.05o", lambda ls: ls.__delitem__(slice(862, 865))))
    with pytest.raises(GnssFileError, match=r"e\.05o, line 857: epoch truncated: G24 has no observation line"):
        read_obs(_write_lines(DATA / "07590920.05o", tmp_path / "e.05o", lambda ls: ls.__delitem__(slice(863, None))))
    with pytest.raises(GnssFileError, match=r"c\.clk, line 21: cannot read a number"):
        read_clk(_write_lines(DATA / "igs15904.clk", tmp_path / "c.clk",
                              lambda ls: ls.__setitem__(20, ls[20][:40] + "x.y" + ls[20][43:])))
    (tmp_path / "e.sp3").write_text("")
    with pytest.raises(GnssFileError, match=r"e\.sp3: empty file"):
        read_sp3(tmp_path / "e.sp3")
