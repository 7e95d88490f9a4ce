"""Seed 000 with the adaptive process noise of eq 7 (filters/adaptive.py) in the loop.

A mismodelled clock (the simulated clock's N_eps 1e4 x the filter's): without eq 7 the
clock block's NEES is far outside any chi-square band; with eq 7 on the dynamic states it
is back near 1 per dof. On a correctly modelled clock eq 7 on the dynamic states changes
the I_g/U_g result little, while eq 7 on every state (the seed's choice) slows I_g/U_g
(it re-inflates their variance by 0.7 (W nu)^2 every epoch). Also the study runner and
the `--study` command line.
"""
import dataclasses
import json

import numpy as np
import pytest
import scipy.stats

from sitl.app.cli import main
from sitl.app.experiments.iono_tropo_filters import IonoTropoScenario, run_streamed
from sitl.app.experiments.iono_tropo_studies import adaptive_q_study, ordering_study

TRIALS = 8


@pytest.fixture(scope="module")
def mismodelled():
    base = IonoTropoScenario(duration_s=60.0, truth_clock_psd_scale=1e4)
    off = run_streamed(base, TRIALS, seed=5, variant=1)
    dyn = run_streamed(dataclasses.replace(base, adaptive_q=True, adaptive_q_scope="dynamic"), TRIALS, seed=5,
                       variant=1)
    return off, dyn


@pytest.mark.slow
def test_eq7_restores_clock_consistency(mismodelled):
    off, dyn = mismodelled
    hi = scipy.stats.chi2.ppf(0.9995, 2 * TRIALS) / TRIALS / 2  # per dof, one epoch
    assert off["anees_clock"] > 20 * hi, off["anees_clock"]
    assert dyn["anees_clock"] < hi, dyn["anees_clock"]


@pytest.mark.slow
def test_same_data_whatever_the_filter(mismodelled):
    off, dyn = mismodelled
    np.testing.assert_array_equal(off["n_visible"], dyn["n_visible"])
    assert off["prior_error"] == dyn["prior_error"]


def test_eq7_off_by_default_and_scope_is_validated():
    assert IonoTropoScenario(duration_s=1.0).adaptive_q is False
    with pytest.raises(ValueError, match="adaptive_q_scope"):
        IonoTropoScenario(duration_s=1.0, adaptive_q_scope="some")
    with pytest.raises(ValueError, match="adaptive_q_decay"):
        IonoTropoScenario(duration_s=1.0, adaptive_q_decay=1.0)


def test_study_runners_shape():
    base = IonoTropoScenario(duration_s=5.0)
    st = adaptive_q_study(base, 2, 0, variants=(1,))
    assert len(st["rows"]) == 6
    assert {(r["config"], r["clock"]) for r in st["rows"]} == {
        (c, k) for c in ("off", "eq7_all_states", "eq7_dynamic_states") for k in ("nominal", "mismodelled")}
    od = ordering_study(base, [0, 1], 2)
    assert od["of"] == 2 and len(od["per_seed"]) == 2
    with pytest.raises(ValueError, match="clock_scale"):
        adaptive_q_study(base, 2, 0, clock_scale=0.5)


def test_study_command_line(tmp_path, capsys):
    assert main(["experiment", "iono-tropo", "--study", "ordering", "--seeds", "2", "--trials", "2", "--duration", "5",
                 "--quiet", "--out", str(tmp_path)]) == 0
    doc = json.loads((tmp_path / "ordering_study.json").read_text())
    assert doc["study"] == "ordering" and doc["of"] == 2
    assert (tmp_path / "ordering_study.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "holds for" in capsys.readouterr().out
