"""RINEX 3.04 export of the simulated world (sitl.gnss.rinex_write, sitl.app.gnss.export):
georinex reads back what was written (to the format's precision), the navigation records
reproduce the simulated orbits, RTKLIB's rnx2rtkp solves the exported files to the truth within
the noise, and bad command lines end in one line, exit 2."""
from __future__ import annotations

import shutil
import warnings
from datetime import datetime, timedelta

import numpy as np
import pytest

from sitl.constants import C_M_S, GPS_UTC_LEAP_S
from sitl.gnss import rinex_write as rw
from sitl.gnss.orbits import DEFAULT_TOA_GPS_S, Constellation, default_constellation, sat_state_ecef

georinex = pytest.importorskip("georinex", reason="georinex is not installed (the RINEX reader of the round trip)")

T0 = DEFAULT_TOA_GPS_S + 3600.0  # the default scenario's start
GPS_EPOCH = datetime(1980, 1, 6)


def _load(path, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return georinex.load(path, **kw)


def _dt64(t_gps_s, leap=0.0):
    return np.datetime64(GPS_EPOCH + timedelta(seconds=float(t_gps_s - leap)), "us")


# ------------------------------------------------------------------------------------ observations

def test_obs_round_trip_georinex(tmp_path):
    rng = np.random.default_rng(24)
    const = default_constellation("GR")
    ids = const.sat_id
    T, S = 12, len(ids)
    tag = T0 + np.arange(T) * 1.0
    pr = rng.uniform(19e6, 26e6, (T, S))
    ph = pr / 0.19 + rng.integers(-10**6, 10**6, (T, S))
    dop = rng.uniform(-4500, 4500, (T, S))
    snr = np.full((T, S), 45.0)
    vis = rng.random((T, S)) < 0.4
    for a in (pr, ph, dop, snr):
        a[~vis] = np.nan
    lli = (rng.random((T, S)) < 0.1).astype(int)
    path = rw.write_obs(tmp_path / "x.obs", tag, ids, const.glonass_k, pr, ph, dop, snr, lli,
                        approx_pos_ecef_m=(2840561.0, 2181215.0, 5260237.0), interval_s=1.0)
    text = path.read_text()
    assert "GLONASS SLOT / FRQ #" in text and "GLONASS COD/PHS/BIS" in text
    assert " 24 R01  1 R02 -4" in text  # the FDMA channels of orbits.GLONASS_SLOT_K
    ds = _load(path)
    assert ds.attrs["version"] == pytest.approx(3.04)
    assert list(ds.time.values) == [_dt64(t) for t in tag]
    col = {s: j for j, s in enumerate(ids)}
    for name, ref, tol in (("C1C", pr, 5e-4), ("L1C", ph, 5e-4), ("D1C", dop, 5e-4), ("S1C", snr, 5e-4)):
        got = np.full((T, S), np.nan)
        for q, sv in enumerate(ds.sv.values):
            got[:, col[str(sv)]] = ds[name].values[:, q]
        assert np.array_equal(np.isnan(got), np.isnan(ref)), name
        np.testing.assert_allclose(got[vis], ref[vis], rtol=0, atol=tol, err_msg=name)


# ------------------------------------------------------------------------------------ navigation

@pytest.fixture(scope="module")
def nav(tmp_path_factory):
    const = default_constellation("GR")
    toes_g = T0 + np.array([0.0, 900.0])
    toes_r = T0 + GPS_UTC_LEAP_S + np.array([0.0, 900.0])
    g, clk_res = rw.gps_lnav_records(const, toes_g, 450.0)
    r, fit_max, _ = rw.glonass_records(const, toes_r, 450.0)
    alpha, beta = rw.klobuchar_constant(15.0)
    path = rw.write_nav(tmp_path_factory.mktemp("nav") / "x.nav", g, r, iono_alpha=alpha, iono_beta=beta)
    return const, g, r, clk_res, fit_max, path


def test_nav_round_trip_georinex(nav):
    const, g, r, _, _, path = nav
    ds = _load(path)
    rec = g[0]
    row = ds.sel(sv=rec["sat_id"], time=_dt64(rec["toe_gps_s"]))
    for name, key in (("SVclockBias", "af0"), ("SVclockDrift", "af1"), ("SVclockDriftRate", "af2"), ("M0", "m0"),
                      ("Eccentricity", "e"), ("sqrtA", "sqrt_a"), ("Toe", "toe_sow"), ("Omega0", "omega0"),
                      ("Io", "i0"), ("omega", "omega"), ("OmegaDot", "omega_dot"), ("GPSWeek", "week")):
        assert float(row[name]) == pytest.approx(float(rec[key]), rel=1e-11, abs=1e-30), name
    rec = r[-1]
    row = ds.sel(sv=rec["sat_id"], time=_dt64(rec["toe_gps_s"], GPS_UTC_LEAP_S))  # GLONASS epochs: UTC
    for q, ax in enumerate("XYZ"):  # georinex gives metres
        assert float(row[ax]) == pytest.approx(rec["pos_m"][q], abs=1e-5)
        assert float(row["d" + ax]) == pytest.approx(rec["vel_m_s"][q], abs=1e-8)
        assert float(row["d" + ax + "2"]) == pytest.approx(rec["acc_m_s2"][q], rel=1e-11, abs=1e-16)
    assert int(row["FreqNum"]) == rec["k"]
    head = path.read_text().split("END OF HEADER")[0]
    assert "GPSA" in head and "GPSB" in head


def test_gps_records_reproduce_the_simulated_orbits(nav):
    """The elements as read back, propagated by the IS-GPS-200 algorithm, are the simulated orbit."""
    const, g, _, clk_res, _, path = nav
    ds = _load(path)
    gps = const.subset(const.system == "G")
    for rec in g[len(gps):]:  # the second t_oe: elements moved 900 s from those of the first
        row = ds.sel(sv=rec["sat_id"], time=_dt64(rec["toe_gps_s"]))
        one = Constellation(sat_id=[rec["sat_id"]], system=["G"], toa_gps_s=[rec["week"] * 604800.0 + float(row["Toe"])],
                            a_m=[float(row["sqrtA"]) ** 2], e=[float(row["Eccentricity"])], i_rad=[float(row["Io"])],
                            Omega0_rad=[float(row["Omega0"])], OmegaDot_rad_s=[float(row["OmegaDot"])],
                            omega_rad=[float(row["omega"])], M0_rad=[float(row["M0"])], glonass_k=[0])
        t = rec["toe_gps_s"] + np.linspace(-450.0, 450.0, 7)
        p_nav, _ = sat_state_ecef(one, t)
        p_sim, _ = sat_state_ecef(gps.subset(rec["sat_id"]), t)
        assert np.max(np.linalg.norm(p_nav - p_sim, axis=-1)) < 1e-3  # D19.12: 12 digits
    assert clk_res * C_M_S < 1e-3  # the relativistic term folded into af0..af2, within 1 mm


def test_glonass_records_follow_the_simulated_orbits(nav):
    """RTKLIB's integration of the records (replica) against the simulated orbit over t_b +/- 450 s:
    the constant-acceleration model cannot carry the Keplerian orbit exactly (the simulated
    GLONASS orbit lacks the J2 short-period terms the ICD model integrates): < 0.3 m."""
    const, _, r, _, fit_max, _ = nav
    assert fit_max < 0.3
    glo = const.subset(const.system == "R")
    rec = r[3]
    for dt in (-450.0, -125.0, 0.0, 333.0, 450.0):
        p = rw.glonass_orbit(np.r_[rec["pos_m"], rec["vel_m_s"]], rec["acc_m_s2"], dt)
        p_sim, _ = sat_state_ecef(glo.subset(rec["sat_id"]), rec["toe_gps_s"] + dt)
        assert np.linalg.norm(p - p_sim[0]) < 0.3


def test_klobuchar_flat():
    alpha, beta = rw.klobuchar_constant(15.0)
    assert alpha[0] == pytest.approx(15.0 / C_M_S - 5e-9) and beta[0] == rw.KLOBUCHAR_FLAT_PER_S
    assert rw.klobuchar_constant(1.0) is None


# ------------------------------------------------------------------------------------ the command

export_mod = pytest.importorskip("sitl.app.gnss.export")


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    out = tmp_path_factory.mktemp("export")
    assert export_mod.main(["--duration", "600", "--no-iono", "--no-tropo", "--out", str(out)]) == 0
    return out


def test_export_files_and_truth(exported):
    for name in ("sim.obs", "sim.nav", "truth.csv", "truth_geometry.npz", "export.json"):
        assert (exported / name).is_file()
    truth = np.genfromtxt(exported / "truth.csv", delimiter=",", names=True)
    assert truth.size == 601
    # the RINEX tag is receiver time: true time + clock bias / c
    np.testing.assert_allclose(truth["rinex_tag_gps_s"] - truth["t_gps_s"], truth["clock_bias_m"] / C_M_S, atol=5e-7)
    ds = _load(exported / "sim.obs", tlim=(str(_dt64(T0)), str(_dt64(T0 + 4))))
    n = np.isfinite(ds["C1C"].values).sum(axis=1)
    np.testing.assert_array_equal(n, (truth["n_gps"] + truth["n_glonass"])[: n.size])


def test_export_deterministic(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    for d in (a, b):
        assert export_mod.main(["--duration", "20", "--out", str(d)]) == 0
    assert (a / "sim.obs").read_bytes() == (b / "sim.obs").read_bytes()
    assert (a / "sim.nav").read_bytes() == (b / "sim.nav").read_bytes()


@pytest.mark.skipif(shutil.which("rnx2rtkp") is None, reason="RTKLIB's rnx2rtkp is not installed (apt-get install rtklib)")
@pytest.mark.parametrize("systems", ["GR", "G"])
def test_rtklib_solves_the_export_to_the_noise(exported, systems):
    """Atmosphere off, RTKLIB's corrections off: its single-point error has no bias beyond the noise
    and the scatter the truth geometry predicts (sigma * DOP)."""
    r = export_mod.score(exported, export_mod.run_rnx2rtkp(exported, systems), systems)
    assert r["epochs"] == 601
    pred = np.array(r["predicted_std_enu_m_rtklib_weights"])
    std, mean = np.array(r["std_enu_m"]), np.array(r["mean_enu_m"])
    assert np.all(np.abs(mean) < 4.0 * pred / np.sqrt(r["epochs"]) + 0.05), r
    assert np.all((std > 0.85 * pred) & (std < 1.15 * pred)), r


@pytest.mark.parametrize("argv, what", [
    (["--receiver", "car"], "invalid choice"),
    (["--duration", "-5"], "--duration"),
])
def test_bad_input_one_line_exit_2(tmp_path, capsys, argv, what):
    assert export_mod.main(argv + ["--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and what in err


def test_unwritable_out_one_line_exit_2(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert export_mod.main(["--duration", "5", "--out", str(blocker / "sub")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--out" in err
