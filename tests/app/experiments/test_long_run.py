"""`skyfuse experiment long-run` (issue 19, item 4): the default scenario as `demo --batch` runs
it, the beacon's window RMSE against its PCRB and its ANEES against the chi-square band.

* a trial is exactly the batch demo run (same components and seeds: the same errors);
* the window checks on synthetic errors of known covariance: consistent errors pass, errors 3x
  too large fail both checks, 5x too small fail the ANEES one;
* the CLI's short run on the default geometry passes every window and writes its files;
* the old configuration (UAVs northbound, beacon on its legs, the "inflate" locator) run long
  enough is flagged: its early windows pass, the late ones (the beacon 70-110 km from the
  formation) fail -- the check can fail on the case the issue was about;
* bad flags exit 2 with one line.
"""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from sitl.app import cli
from sitl.app.experiments import long_run as lr


@pytest.mark.slow
def test_a_trial_is_the_batch_demo_run():
    from sitl.app.batch import run_batch

    scn = lr.scenario_for("default", 40.0, seed=3)
    trial = lr.run_trial(scn)
    ref = run_batch(scn)["errors"]
    for name, d in (("beacon/b1", trial["beacon"]), ("sonde/s0000", trial["sonde"])):
        e = np.linalg.norm(d["x"][:, 0:3] - d["truth"][:, 0:3], axis=-1)
        e = e[np.isfinite(e)]
        assert e.size == ref[name]["scored"] > 30
        assert math.sqrt(np.mean(e ** 2)) == pytest.approx(ref[name]["rmse_m"], rel=1e-12)
    assert np.all(np.isfinite(trial["U"])) and trial["U"].shape == (41, 3, 3)


def test_window_checks_on_errors_of_known_covariance():
    rng = np.random.default_rng(5)
    K, T = 1201, 4
    t = np.arange(K, dtype=float)
    sig = np.array([4.0, 6.0, 12.0])
    P = np.diag(sig ** 2)
    e = rng.standard_normal((K, T, 3)) * sig
    sq = np.full(K, math.sqrt(np.trace(P)))

    def check(scale):
        es = scale * e
        nees = np.einsum("kti,ij,ktj->kt", es, np.linalg.inv(P), es)
        return lr.windows(t, np.linalg.norm(es, axis=-1), nees, sq, 600.0, 100.0, T)

    ok = check(1.0)
    assert [w["t_start_s"] for w in ok] == [0.0, 600.0] and ok[-1]["t_end_s"] == K - 1  # the last epoch in the last
    assert all(w["pass"] for w in ok)
    assert all(0.8 < w["rmse_ratio"] < 1.2 and 2.6 < w["anees"] < 3.4 for w in ok)
    lo, hi = ok[0]["band"]
    assert lo == pytest.approx(0.768, abs=0.01) and hi == pytest.approx(7.07, abs=0.02)  # chi2(12) / 4, 99 %
    big = check(3.0)
    assert not any(w["rmse_pass"] or w["anees_pass"] or w["pass"] for w in big)
    small = check(0.2)
    assert all(w["rmse_pass"] and not w["anees_pass"] and not w["pass"] for w in small)
    # without the bound: against twice the first window's RMSE
    nees = np.einsum("kti,ij,ktj->kt", e, np.linalg.inv(P), e)
    err = np.linalg.norm(e, axis=-1)
    err[700:] *= 3.0
    nb = lr.windows(t, err, nees, None, 600.0, 100.0, T)
    assert nb[0]["reference"] == "first_window" and nb[0]["rmse_pass"] and not nb[1]["rmse_pass"]


@pytest.mark.slow
def test_cli_short_run_on_the_default_geometry_passes(tmp_path, capsys):
    out = tmp_path / "lr"
    rc = cli.main(["experiment", "long-run", "--duration", "400", "--window", "400", "--trials", "1", "--no-sonde",
                   "--seed", "2", "--out", str(out), "--quiet"])
    assert rc == 0
    doc = json.loads((out / "result.json").read_text())
    assert (out / "long_run.png").stat().st_size > 10_000
    assert doc["locator_config"]["observer_uncertainty"] == "consider"  # the live ground station's
    assert doc["scenario"]["uavs"]["pattern"] == "orbit" and doc["scenario"]["beacon"]["mode"] == "racetrack"
    (w,) = doc["windows"]
    assert w["t_start_s"] == 0.0 and w["t_end_s"] == 400.0 and w["epochs"] == 301  # scored from 100 s
    assert w["sqrt_pcrb_m"] > 0 and w["rmse_m"] <= 2.0 * w["sqrt_pcrb_m"] and w["anees_pass"]
    assert doc["all_windows_pass"] and doc["windows_failed"] == []
    assert "ALL WINDOWS PASS" in capsys.readouterr().out


@pytest.mark.slow
def test_old_northbound_inflate_configuration_is_flagged():
    doc = lr.long_run(1800.0, seed=1, trials=1, geometry="north", locator="inflate", with_sonde=False)
    win = doc["windows"]
    assert len(win) == 3 and doc["locator_config"]["observer_uncertainty"] == "inflate"
    assert win[0]["pass"]  # while the beacon is near the UAVs
    assert not win[-1]["pass"] and 2 in doc["windows_failed"]
    assert win[-1]["beacon_to_uav_centroid_km"][1] > 100.0
    assert win[-1]["rmse_m"] > 2.0 * win[-1]["sqrt_pcrb_m"] and win[-1]["anees"] > win[-1]["band"][1]


@pytest.mark.parametrize("flags", [["--duration", "0"], ["--duration", "500", "--window", "600"],
                                   ["--window", "100", "--settle", "100"], ["--trials", "0"],
                                   ["--geometry", "east"]])
def test_bad_flags_exit_2_with_one_line(tmp_path, capsys, flags):
    rc = cli.main(["experiment", "long-run", "--out", str(tmp_path / "x"), *flags])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1, err
