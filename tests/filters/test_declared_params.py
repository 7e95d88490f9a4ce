"""The filters' declared parameters: one bad value per class gives a one-line ParamError
naming the field; every declared field has a doc."""
from __future__ import annotations

import numpy as np
import pytest

from filters import adaptive, beacon, cycleslip, integrity, iono_tropo, models, ukf
from filters.params import ParamError, checks, docs

SP, SV = np.ones((4, 3)) * 2e7, np.zeros((4, 3))
U = np.array([[1e4, 0, 0], [0, 1e4, 0], [0, 0, 1e4]], float)

BAD = [
    (lambda: models.ConstantVelocity(0, q=1.0), "ndim_pos"),
    (lambda: models.ConstantAcceleration(3, q=np.nan), "q"),
    (lambda: models.Singer(0.2, 5.0, ndim_pos=True), "ndim_pos"),
    (lambda: models.ClockGaussMarkov(0.1, 3.0, exact_bias="yes"), "exact_bias"),
    (lambda: models.ClockRandomWalk(1e-20, c=-1.0), "c"),
    (lambda: models.Composite((), None), "blocks"),
    (lambda: models.LinearGaussian(np.ones(3), np.eye(3)), "H_matrix"),
    (lambda: models.PseudorangeDoppler(SP, SV, 3.0, 0.1, n=0), "n"),
    (lambda: models.PseudorangeDoppler(SP, SV, np.full((4, 4), -1.0), 0.1), "sigma_pr_m"),
    (lambda: models.ClockFreePseudorangeDoppler(SP, SV, 0.0, 1.0), "var_pr_m2"),
    (lambda: iono_tropo.IonoTropoTransition(n_amb=-1), "n_amb"),
    (lambda: iono_tropo.IonoTropoGnss(SP, SV, np.full(4, 1.6e9), np.ones(4, bool), 3.0, 0.1, n_state=5), "n_state"),
    (lambda: beacon.ObserverRangeDoppler(U, U, 1.0, 1.0, observer_uncertainty="maybe"), "observer_uncertainty"),
    (lambda: ukf.SigmaPoints(3, beta=np.inf), "beta"),
    (lambda: integrity.IntegrityConfig(window_alpha=1.0), "window_alpha"),
    (lambda: cycleslip.CycleSlipConfig(max_dt_s="1"), "max_dt_s"),
    (lambda: adaptive.AdaptiveQ(states=3), "states"),
]


@pytest.mark.parametrize("make, key", BAD, ids=[k for _, k in BAD])
def test_a_bad_value_is_a_one_line_error_naming_the_field(make, key):
    with pytest.raises(ParamError) as err:
        make()
    assert err.value.key == key and str(err.value).startswith(f"{key}: ") and "\n" not in str(err.value)


CLASSES = [models.ConstantVelocity, models.ConstantAcceleration, models.Singer, models.ClockGaussMarkov,
           models.ClockRandomWalk, models.Composite, models.LinearGaussian, models.PseudorangeDoppler,
           models.ClockFreePseudorangeDoppler, iono_tropo.IonoTropoTransition, iono_tropo.IonoTropoGnss,
           beacon.ObserverRangeDoppler, ukf.SigmaPoints, integrity.IntegrityConfig, cycleslip.CycleSlipConfig,
           adaptive.AdaptiveQ]


@pytest.mark.parametrize("cls", CLASSES, ids=[c.__name__ for c in CLASSES])
def test_every_declared_field_has_a_doc(cls):
    assert checks(cls) and all(len(d) > 5 for d in docs(cls).values())


def test_stored_types():
    assert type(models.Singer(1, 5).alpha_1_s) is float
    assert type(iono_tropo.IonoTropoTransition(n_amb=np.int64(2)).n_amb) is int
    m = models.PseudorangeDoppler(SP, SV, 3, np.full(4, 0.1))
    assert type(m.sigma_pr_m) is float and not m.sigma_prr_m_s.flags.writeable
    assert np.shares_memory(m.sat_pos_ecef_m, SP)
    assert models.PseudorangeDoppler(SP, SV, 3.0, 0.1, idx_pos=slice(0, 3)).idx_pos == (0, 1, 2)
