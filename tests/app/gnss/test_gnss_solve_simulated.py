"""`skyfuse gnss solve` on the simulated world written as RINEX (`skyfuse gnss export`, static
receiver, 600 s at 1 Hz, GPS + GLONASS, iono 15 m and tropo 2.5 m at the zenith on the seed's
mappings): where the filter's model is the truth's, the carrier-phase variant must find the
simulator's zenith delays and position (export.json, truth.csv: the simulator's own truth, not
the filter's), which checks the whole real-data path -- RINEX 3 codes, broadcast states, light
time, Sagnac, TGD, the phase rows and their ambiguities -- end to end. The file's Doppler (D1C)
feeds the code_doppler variant's rate rows."""
from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from sitl.app.cli import main


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    d = tmp_path_factory.mktemp("export")
    assert main(["gnss", "export", "--receiver", "static", "--duration", "600", "--out", str(d)]) == 0
    with open(d / "truth.csv") as f:
        row = next(csv.DictReader(f))
    truth = {"pos": [float(row[k]) for k in ("x_m", "y_m", "z_m")],
             "atmosphere": json.loads((d / "export.json").read_text())["atmosphere"]}
    return d, truth


def _solve(exported, tmp_path, variant):
    d, truth = exported
    ref = ",".join(f"{v:.4f}" for v in truth["pos"])
    out = tmp_path / variant
    rc = main(["gnss", "solve", str(d / "sim.obs"), "--nav", str(d / "sim.nav"), "--variant", variant, "--static",
               "--iono-shape", "thin_shell", "--sigma-pr-m", "6", "--sigma-phase-m", "0.003", "--reference-ecef", ref,
               "--no-rtklib", "--quiet", "--out", str(out)])
    assert rc == 0
    return json.loads((out / "result.json").read_text())


def test_carrier_phase_finds_the_simulated_atmosphere_and_position(exported, tmp_path):
    _, truth = exported
    r = _solve(exported, tmp_path, "carrier_phase")
    s = r["series"]
    iono_true = truth["atmosphere"]["iono"]["zenith_m_at_gps_l1"]
    tropo_true = truth["atmosphere"]["tropo"]["zenith_m"]
    assert (iono_true, tropo_true) == (15.0, 2.5)
    # the last epoch: within 4 sigma of the filter's own sd, and close in metres
    assert abs(s["iono_zenith_m"][-1] - iono_true) < max(4 * s["iono_sd_m"][-1], 0.02)
    assert abs(s["tropo_zenith_m"][-1] - tropo_true) < max(4 * s["tropo_sd_m"][-1], 0.005)
    assert abs(s["iono_zenith_m"][-1] - iono_true) < 0.1 and abs(s["tropo_zenith_m"][-1] - tropo_true) < 0.02
    enu = np.array(s["enu_error_m"], dtype=float)
    assert np.max(np.abs(enu[300:])) < 0.2  # after 5 min: centimetres, not metres
    assert r["counts"]["non_gps_satellites"] > 0  # GLONASS in the file, counted and left out


def test_code_doppler_uses_the_file_doppler(exported, tmp_path):
    r = _solve(exported, tmp_path, "code_doppler")
    assert r["counts"]["rate_rows"] > 5000  # D1C on every tracked satellite-epoch, not the phase rate
    pe = r["position_error_m"]
    assert pe["rms_3d"] < 5.0  # 10 min of 6 m code: metres, converging
    assert max(abs(v) for v in pe["mean_enu"]) < 3.0
