"""sitl.gnss.klobuchar against the IS-GPS-200 algorithm (20.3.3.5.2.5, Figure 20-4) transcribed
here step by step in scalar form, and against values that follow from the ICD by hand: the night
floor c F 5 ns, the afternoon peak c F (5 ns + AMP) at local time 14:00, the amplitude and period
clamps. Coefficients: the ION ALPHA/BETA of tests/data/gnss/07590920.05n."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from sitl.gnss.klobuchar import klobuchar_delay_m
from sitl.gnss.rinex_nav import read_nav

DATA = Path(__file__).resolve().parents[2] / "data" / "gnss"
C = 299_792_458.0


def icd_delay_s(alpha, beta, lat_sc, lon_sc, az_sc, el_sc, t_s):
    """IS-GPS-200 Figure 20-4 in the ICD's own units (semicircles), one line of sight."""
    psi = 0.0137 / (el_sc + 0.11) - 0.022
    phi_i = lat_sc + psi * math.cos(az_sc * math.pi)
    if phi_i > 0.416:
        phi_i = 0.416
    elif phi_i < -0.416:
        phi_i = -0.416
    lam_i = lon_sc + psi * math.sin(az_sc * math.pi) / math.cos(phi_i * math.pi)
    phi_m = phi_i + 0.064 * math.cos((lam_i - 1.617) * math.pi)
    t = 4.32e4 * lam_i + t_s
    while t >= 86400.0:
        t -= 86400.0
    while t < 0.0:
        t += 86400.0
    f = 1.0 + 16.0 * (0.53 - el_sc) ** 3
    amp = sum(alpha[n] * phi_m**n for n in range(4))
    per = sum(beta[n] * phi_m**n for n in range(4))
    amp = max(amp, 0.0)
    per = max(per, 72000.0)
    x = 2.0 * math.pi * (t - 50400.0) / per
    if abs(x) < 1.57:
        return f * (5.0e-9 + amp * (1.0 - x**2 / 2.0 + x**4 / 24.0))
    return f * 5.0e-9


@pytest.fixture(scope="module")
def coeffs():
    nav = read_nav(DATA / "07590920.05n")
    return nav.ion_alpha, nav.ion_beta


def test_against_the_icd_transcription_on_a_grid(coeffs):
    a, b = coeffs
    rng = np.random.default_rng(24)
    n = 400
    lat = rng.uniform(-1.4, 1.4, n)
    lon = rng.uniform(-math.pi, math.pi, n)
    az = rng.uniform(0, 2 * math.pi, n)
    el = rng.uniform(math.radians(2), math.pi / 2, n)
    t = rng.uniform(0, 7 * 86400.0, n) + 1_300 * 604_800.0
    got = klobuchar_delay_m(a, b, lat, lon, az, el, t)
    want = np.array([C * icd_delay_s(a, b, lat[i] / math.pi, lon[i] / math.pi, az[i] / math.pi, el[i] / math.pi, t[i])
                     for i in range(n)])
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-9)
    assert 0.5 < np.max(got) < 60.0  # metres: a daytime slant delay


def test_night_floor_and_afternoon_peak_by_hand(coeffs):
    a, b = coeffs
    # at the zenith psi = 0.0137/0.61 - 0.022 = 0.000459 semicircles, F = 1 + 16 (0.03)^3 = 1.000432
    F = 1.0 + 16.0 * 0.03**3
    lat, lon = 0.0, 0.0
    psi = 0.0137 / 0.61 - 0.022
    # azimuth 0: lambda_i = 0, phi_i = psi; local time = t: 02:00 is night (|x| > 1.57 for any period >= 72000 s)
    night = klobuchar_delay_m(a, b, lat, lon, 0.0, math.pi / 2, 2 * 3600.0)
    assert night == pytest.approx(C * F * 5e-9, rel=1e-12)  # 1.4996 m
    # 14:00 local time at the pierce point: x = 0, delay = c F (5 ns + AMP(phi_m))
    phi_m = psi + 0.064 * math.cos(-1.617 * math.pi)
    amp = max(sum(a[n] * phi_m**n for n in range(4)), 0.0)
    peak = klobuchar_delay_m(a, b, lat, lon, 0.0, math.pi / 2, 50400.0)
    assert peak == pytest.approx(C * F * (5e-9 + amp), rel=1e-12)
    assert peak > night


def test_clamps_amplitude_and_period():
    # negative amplitude polynomial -> AMP = 0: the delay is the night floor even at 14:00
    d = klobuchar_delay_m([-1e-8, 0, 0, 0], [1e5, 0, 0, 0], 0.0, 0.0, 0.0, math.pi / 2, 50400.0)
    assert d == pytest.approx(C * (1.0 + 16.0 * 0.03**3) * 5e-9, rel=1e-12)
    # a period below 72000 s is raised to 72000 s: 3 h after the peak x = 2 pi 10800 / 72000 = 0.9425
    F = 1.0 + 16.0 * 0.03**3
    psi = 0.0137 / 0.61 - 0.022
    x = 2 * math.pi * 10800.0 / 72000.0
    d = klobuchar_delay_m([1e-8, 0, 0, 0], [1000.0, 0, 0, 0], 0.0, 0.0, 0.0, math.pi / 2, 50400.0 + 10800.0)
    assert psi > 0 and d == pytest.approx(C * F * (5e-9 + 1e-8 * (1 - x**2 / 2 + x**4 / 24)), rel=1e-12)
