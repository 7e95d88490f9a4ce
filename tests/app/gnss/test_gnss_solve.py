"""`skyfuse gnss solve` on station 0759 (tests/data/gnss): the three seed 000 variants on real GPS
L1, scored against references computed without the filter -- RTKLIB's own L1 single-point solution
(rnx2rtkp, run by the command on the same file and mask) and the file's dual-frequency ionosphere
(solve_reference, itself checked against georinex in test_solve_reference.py) -- and the
command's one-line errors.

The issue's targets, asserted as such: carrier_phase 3D RMS <= 1.0 m and a zenith-iono RMS below
Klobuchar's. With --static neither is met on this file (1.07 m; 1.41 m against Klobuchar's 1.20 m):
strict xfails, so meeting them turns the run red until the marks go. Without --static the position
target holds (0.90 m), asserted.

Why they pull against each other on this file (test_reference_position.py): with the ionosphere
removed by the second frequency the static position is +2.1 m up from APPROX POSITION (RTKLIB's
iono-free SPP: +2.17 m), and station 3040, 3.3 km away, shows the same (+1.9 m) while RTKLIB's
fixed baseline puts the two APPROX POSITIONs within 0.2 m of each other: ~2 m of the error comes
with the broadcast orbits and clocks of this hour, not from the ionosphere or the reference. An L1
solution carries that error too; Klobuchar's too-large ionosphere (zenith 2.5-3.6 m against the
dual-frequency 1.7-2.3 m) offsets part of it, so a better ionosphere moves the fix away from APPROX
POSITION. The result.json `iono_free_static` block reports it per run. With the receiver held
(--fixed-position) at that iono-free position, the L1 code alone follows the dual-frequency
ionosphere to 0.23 m RMS; the phase variants held there do not (carrier_phase 2.52 m,
phase_increments 2.90 m): their phase information, not the code, drives I_g off.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from sitl.app.cli import main
from sitl.app.gnss.solve_reference import rnx2rtkp_path

DATA = Path(__file__).resolve().parents[2] / "data" / "gnss"
OBS, NAV = str(DATA / "07590920.05o"), str(DATA / "07590920.05n")
HAVE_RTKLIB = rnx2rtkp_path() is not None


def _solve(out: Path, variant: str, *extra: str) -> dict:
    rc = main(["gnss", "solve", OBS, "--nav", NAV, "--variant", variant, "--static", "--quiet", "--out", str(out),
               *extra])
    assert rc == 0
    return json.loads((out / "result.json").read_text())


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    base = tmp_path_factory.mktemp("solve")
    return {v: _solve(base / v, v) for v in ("code_doppler", "phase_increments", "carrier_phase")}


def test_result_holds_the_blocks_and_a_plot(runs, tmp_path):
    r = runs["carrier_phase"]
    pe = r["position_error_m"]
    assert len(pe["mean_enu"]) == 3 and len(pe["std_enu"]) == 3 and pe["epochs"] == 120
    s = r["series"]
    assert len(s["iono_zenith_m"]) == len(s["tropo_zenith_m"]) == len(s["t_gps_s"]) == 120
    ir = r["iono_reference"]
    assert len(ir["dual_frequency_zenith_m"]) == 120
    assert "least squares" in ir["receiver_code_bias"]["treatment"]
    assert r["reference"]["source"].startswith("APPROX POSITION")
    assert r["timing_s"]["read_and_process"] > 0
    out = tmp_path / "plot"
    _solve(out, "carrier_phase", "--no-rtklib")
    assert (out / "solve.png").stat().st_size > 10_000
    assert json.loads((out / "result.json").read_text())["rtklib"] == {"skipped": "--no-rtklib"}


@pytest.mark.skipif(not HAVE_RTKLIB, reason="rnx2rtkp not installed (Debian package rtklib)")
def test_rtklib_block_is_the_issue_figure(runs):
    rt = runs["carrier_phase"]["rtklib"]
    assert rt["l1_spp_rms_3d_m"] == pytest.approx(1.21, abs=0.01)
    assert rt["epochs"] == 120


@pytest.mark.skipif(not HAVE_RTKLIB, reason="rnx2rtkp not installed (Debian package rtklib)")
def test_carrier_phase_beats_rtklib_single_point(runs):
    """The carrier-phase variant against RTKLIB's L1 SPP (Klobuchar + Saastamoinen, same mask):
    a smaller 3D RMS and a smaller scatter on every axis."""
    r = runs["carrier_phase"]
    rt = r["rtklib"]
    assert r["position_error_m"]["rms_3d"] < rt["l1_spp_rms_3d_m"]
    for ours, theirs in zip(r["position_error_m"]["std_enu"], rt["std_enu"]):
        assert ours < theirs + 0.05


def test_variants_order_and_phase_helps(runs):
    """Carrier phase < phase increments < code and rate in 3D RMS on this file (the seed's ordering)."""
    rms = {v: r["position_error_m"]["rms_3d"] for v, r in runs.items()}
    assert rms["carrier_phase"] < rms["phase_increments"] < rms["code_doppler"]


def test_zenith_estimates_are_physical(runs):
    """Zenith delays of the right size once converged (after 10 min): L1 iono 0..10 m, tropo 1.5..3.5 m
    (a sea-level zenith delay is ~2.3-2.6 m), and the phase variants' I_g within 2 m of the
    dual-frequency reference at every epoch (the RMS against it is in the xfail below)."""
    for v, r in runs.items():
        s, ir = r["series"], r["iono_reference"]
        late = [k for k, t in enumerate(s["t_gps_s"]) if t - s["t_gps_s"][0] >= 600.0]
        assert all(0.0 < s["iono_zenith_m"][k] < 10.0 for k in late), v
        assert all(1.5 < s["tropo_zenith_m"][k] < 3.5 for k in late), v
        if v != "code_doppler":
            assert all(abs(s["iono_zenith_m"][k] - ir["dual_frequency_zenith_m"][k]) < 2.0 for k in late), v


@pytest.mark.xfail(strict=True, reason="issue 24 target not met with --static: carrier_phase 1.07 m 3D RMS on 0759; "
                                       "the iono-free fix of the same file is 2.1 m off APPROX POSITION (module doc)")
def test_target_carrier_phase_within_one_metre_static(runs):
    assert runs["carrier_phase"]["position_error_m"]["rms_3d"] <= 1.0


def test_target_carrier_phase_within_one_metre_moving_receiver_model(tmp_path):
    """Without --static (constant velocity, q_accel 1e-4 m^2/s^3) the target holds on 0759: 0.90 m.
    The slowly varying model errors (one-zenith atmosphere, broadcast orbits) then go partly into a
    slow wander of the position instead of a bias."""
    rc = main(["gnss", "solve", OBS, "--nav", NAV, "--variant", "carrier_phase", "--no-rtklib", "--quiet",
               "--out", str(tmp_path)])
    assert rc == 0
    assert json.loads((tmp_path / "result.json").read_text())["position_error_m"]["rms_3d"] <= 1.0


@pytest.mark.xfail(strict=True, reason="issue 24 target not met: carrier_phase I_g 1.41 m RMS vs Klobuchar 1.20 m "
                                       "(code_doppler's 1.07 m is below it); the phase rows fit the slant iono's "
                                       "change that one zenith value cannot hold (0.40 m RMS misfit, sigma 5 cm)")
def test_target_zenith_iono_below_klobuchar(runs):
    ir = runs["carrier_phase"]["iono_reference"]
    assert ir["rms_estimate_m"] < ir["rms_klobuchar_m"]


def test_code_doppler_static_iono_below_klobuchar(runs):
    """The zenith-iono part of the target is met by code_doppler with --static on this file (1.07 m
    against Klobuchar's 1.20 m), not by the phase variants (xfail above; phase_increments 1.26 m)."""
    ir = runs["code_doppler"]["iono_reference"]
    assert ir["rms_estimate_m"] < ir["rms_klobuchar_m"]


def test_iono_free_block_is_reported(runs):
    """The iono-free static fix is in result.json (its figures are checked against RTKLIB in
    test_reference_position.py) and, where rnx2rtkp is installed, RTKLIB's iono-free SPP beside it."""
    fx = runs["carrier_phase"]["iono_free_static"]
    assert len(fx["enu_error_m"]) == 3 and fx["epochs"] == 120
    assert fx["by_satellite"] and all(s.startswith("G") for s in fx["by_satellite"])
    if HAVE_RTKLIB:
        assert len(runs["carrier_phase"]["rtklib"]["iono_free"]["mean_enu"]) == 3


def _one_line_error(capsys, argv):
    with pytest.raises(SystemExit) as exc:
        rc = main(argv)
        raise SystemExit(rc)
    err = capsys.readouterr().err
    assert exc.value.code == 2 and err.strip().count("\n") == 0 and "Traceback" not in err, err
    return err


def test_bad_input_is_one_line_exit_2(tmp_path, capsys):
    out = str(tmp_path / "o")
    lines = Path(OBS).read_text().splitlines()
    lines[25] = lines[25][:5] + "#" + lines[25][6:]
    (tmp_path / "g.05o").write_text("\n".join(lines) + "\n")
    err = _one_line_error(capsys, ["gnss", "solve", str(tmp_path / "g.05o"), "--nav", NAV, "--out", out])
    assert "g.05o, line 26" in err
    # a navigation file of another day: no record in force at any epoch
    err = _one_line_error(capsys, ["gnss", "solve", OBS, "--nav", str(DATA / "brdc1820.10n"), "--out", out])
    assert "no satellite with a healthy broadcast record" in err
    err = _one_line_error(capsys, ["gnss", "solve", OBS, "--nav", NAV, "--reference-ecef", "1,2", "--out", out])
    assert "X,Y,Z" in err
    err = _one_line_error(capsys, ["gnss", "solve", OBS, "--out", out])
    assert "--nav" in err
    err = _one_line_error(capsys, ["gnss", "solve", str(tmp_path / "missing.05o"), "--nav", NAV, "--out", out])
    assert "missing.05o" in err


def test_code_sigma_laws():
    """sigma / sin el, and RTKLIB's a^2 + b^2 / sin^2 el with a = b: equal at the zenith; at 30 deg
    2 sigma and sqrt(5/2) sigma."""
    from sitl.app.gnss.solve_filter import code_sigma_m

    s = np.array([1.0, 0.5])
    np.testing.assert_allclose(code_sigma_m(0.6, s, "sin"), [0.6, 1.2])
    np.testing.assert_allclose(code_sigma_m(0.6, s, "rtklib"), [0.6, 0.6 * math.sqrt(2.5)])
    with pytest.raises(ValueError):
        code_sigma_m(0.6, s, "cos")


def test_fixed_position_code_recovers_the_dual_frequency_iono_at_the_iono_free_position(tmp_path):
    """--fixed-position (RTKLIB's fixed mode) on code_doppler: held at the file's own iono-free
    static position, the L1 code's zenith iono follows the dual-frequency reference to 0.23 m RMS
    (Klobuchar 1.20 m); held at APPROX POSITION, 2.1 m below it, the same filter is 1.34 m off.
    The L1 iono estimate is as good as the geometry it is given: free, the position and I_g trade
    (up against the iono's elevation pattern) and the broadcast orbits' error goes into both."""
    from sitl.app.gnss.solve_data import prepare
    from sitl.app.gnss.solve_reference import iono_free_static_fix
    from sitl.gnss.rinex_nav import read_nav
    from sitl.gnss.rinex_obs import read_obs

    ep = prepare(read_obs(OBS), read_nav(NAV))
    p_if = iono_free_static_fix(ep, ep.approx_position_m, 10.0)["pos_ecef_m"]
    got = {}
    for name, extra in (("iono_free", ["--reference-ecef=" + ",".join(f"{v:.4f}" for v in p_if)]), ("approx", [])):
        out = tmp_path / name
        rc = main(["gnss", "solve", OBS, "--nav", NAV, "--variant", "code_doppler", "--fixed-position", "--no-rtklib",
                   "--quiet", "--out", str(out), *extra])
        assert rc == 0
        got[name] = json.loads((out / "result.json").read_text())
        assert got[name]["position_error_m"]["rms_3d"] < 1e-6 and got[name]["fixed_position"]
    ir_if, ir_ap = got["iono_free"]["iono_reference"], got["approx"]["iono_reference"]
    assert ir_if["rms_estimate_m"] < 0.5 < ir_if["rms_klobuchar_m"]
    assert ir_ap["rms_estimate_m"] > ir_ap["rms_klobuchar_m"]
