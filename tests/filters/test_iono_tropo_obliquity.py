"""IonoTropoGnss' fixed obliquities (the real-data extension, filters/iono_tropo.py): given the
eq 9 / eq 11 values themselves they reproduce h exactly; given any values they enter h as
I_g k m and U_g m (checked against a scalar computation written here), the iono/tropo columns of
H are those values, and H's position columns are the line of sight only (the obliquity is held
fixed), which central differences of h confirm."""
import math

import numpy as np
import pytest

from filters.iono_tropo import (
    F_REF_HZ, IDX_CLOCK, IDX_IONO, IDX_TROPO, N_BASE, IonoTropoGnss, elevation_rad, iono_mapping, tropo_mapping,
)
from filters.params import ParamError

R_E = 6371e3


def _geometry(rng, S):
    rx = np.array([0.0, 0.0, R_E + 100.0])
    sats = []
    while len(sats) < S:
        p = rng.normal(size=3)
        p = p / np.linalg.norm(p) * 26.56e6
        d = p - rx
        if d[2] / np.linalg.norm(d) > math.sin(math.radians(10)):
            sats.append(p)
    sp = np.array(sats)
    return rx, sp, rng.normal(scale=3e3, size=sp.shape)


def _state(rx, n):
    x = np.zeros(n)
    x[0:3] = rx
    x[IDX_CLOCK] = 1234.5
    x[IDX_IONO] = 4.0
    x[IDX_TROPO] = 2.4
    return x


def test_the_seed_values_given_reproduce_h():
    rng = np.random.default_rng(5)
    rx, sp, sv = _geometry(rng, 6)
    fc = np.full(6, F_REF_HZ)
    gps = np.ones(6, dtype=bool)
    kidx = N_BASE + np.arange(6)
    el = elevation_rad(rx, sp)
    base = IonoTropoGnss(sp, sv, fc, gps, 1.0, 0.1, 0.01, kidx, True)
    fixed = IonoTropoGnss(sp, sv, fc, gps, 1.0, 0.1, 0.01, kidx, True, iono_obliquity=iono_mapping(el),
                          tropo_obliquity=tropo_mapping(el))
    x = _state(rx, N_BASE + 6)
    x[N_BASE:] = rng.normal(scale=10, size=6)
    np.testing.assert_allclose(fixed.h(x), base.h(x), rtol=0, atol=1e-6)


def test_any_values_enter_h_and_H_as_given():
    rng = np.random.default_rng(6)
    S = 5
    rx, sp, sv = _geometry(rng, S)
    mi = rng.uniform(1.0, 3.0, S)
    mu = rng.uniform(1.0, 6.0, S)
    m = IonoTropoGnss(sp, sv, np.full(S, F_REF_HZ), np.ones(S, dtype=bool), 1.0, 0.1, 0.01, N_BASE + np.arange(S),
                      True, iono_obliquity=mi, tropo_obliquity=mu)
    x = _state(rx, N_BASE + S)
    z, H = m.h_and_H(x)
    for j in range(S):
        rho = float(np.linalg.norm(sp[j] - rx))
        assert z[j] == pytest.approx(rho + 1234.5 + 4.0 * mi[j] + 2.4 * mu[j], abs=1e-6)
        assert z[2 * S + j] == pytest.approx(rho + 1234.5 - 4.0 * mi[j] + 2.4 * mu[j], abs=1e-6)
    np.testing.assert_array_equal(H[:S, IDX_IONO], mi)
    np.testing.assert_array_equal(H[:S, IDX_TROPO], mu)
    np.testing.assert_array_equal(H[2 * S:, IDX_IONO], -mi)
    u = (sp - rx) / np.linalg.norm(sp - rx, axis=1, keepdims=True)
    np.testing.assert_allclose(H[:S, 0:3], -u, atol=1e-15)
    # central differences of h in position: the line of sight only, as the obliquity is fixed
    for i in range(3):
        dx = np.zeros_like(x)
        dx[i] = 100.0
        fd = (m.h(x + dx) - m.h(x - dx)) / 200.0
        np.testing.assert_allclose(fd[:S], H[:S, i], rtol=0, atol=1e-8)
    sub = m.subset(np.array([True, False, True, True, False]))
    np.testing.assert_array_equal(sub.iono_obliquity, mi[[0, 2, 3]])
    np.testing.assert_array_equal(sub.tropo_obliquity, mu[[0, 2, 3]])


def test_bad_obliquity_is_one_line():
    rng = np.random.default_rng(7)
    rx, sp, sv = _geometry(rng, 3)
    args = (sp, sv, np.full(3, F_REF_HZ), np.ones(3, dtype=bool), 1.0, 0.1)
    with pytest.raises(ParamError, match="iono_obliquity"):
        IonoTropoGnss(*args, iono_obliquity=np.ones(4))
    with pytest.raises(ParamError, match="tropo_obliquity"):
        IonoTropoGnss(*args, tropo_obliquity=np.array([1.0, -1.0, 1.0]))
