"""The vehicles' configuration dataclasses declare their checks (filters.params): a bad value is
one line ``field: expected ..., got ...`` naming the field, every init field has a doc, and the
stored types are the ones the simulation relies on."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from filters.params import ParamError, docs
from vehicles import uav
from vehicles.mavlink.params import ParamSpec
from vehicles.sonde import SondeParams
from vehicles.uav_nav import GnssNoise, NavConfig

WP = [np.array([[0.5, 0.5, 100.0], [0.51, 0.5, 100.0]])]
CLASSES = (uav.SinusoidalLaw, uav.LegsAndTurns, uav.Racetrack, uav.Hold, uav.WaypointMission, uav.PrintedLaw,
           GnssNoise, NavConfig, SondeParams, ParamSpec)


@pytest.mark.parametrize("make, key", [
    (lambda: uav.SinusoidalLaw(100.0, speed_omega_rad_s=-0.1), "speed_omega_rad_s"),
    (lambda: uav.SinusoidalLaw(np.full(20, 100.0), heading_amp_rad=np.full(20, np.nan)), "heading_amp_rad"),
    (lambda: uav.LegsAndTurns(-1.0, 0.0, [], [0.0]), "speed_m_s"),
    (lambda: uav.LegsAndTurns(1.0, 0.0, [1.0], [0.0]), "turn_rates_rad_s"),
    (lambda: uav.Racetrack(math.radians(95.0), 0.5, 15e3, 100.0), "center_lat_rad"),
    (lambda: uav.Racetrack(0.8, 0.5, 15e3, 100.0, half_length_m=-1.0), "half_length_m"),
    (lambda: uav.Racetrack(0.8, 0.5, 15e3, 100.0, turn_gain_1_s=0.0), "turn_gain_1_s"),
    (lambda: uav.Racetrack(0.8, 0.5, 15e3, 100.0, radial_gain=math.inf), "radial_gain"),
    (lambda: uav.Racetrack(0.8, 0.5, 100.0, 100.0), "radius_m"),
    (lambda: uav.Hold((2, -1)), "batch_shape"),
    (lambda: uav.WaypointMission(WP, 100.0, accept_radius_m=0.0), "accept_radius_m"),
    (lambda: uav.WaypointMission(WP, 100.0, climb_gain_1_s=-1.0), "climb_gain_1_s"),
    (lambda: uav.WaypointMission([np.zeros((0, 3))], 100.0), "waypoints_rad_m[0]"),
    (lambda: uav.WaypointMission(WP, np.ones(2) * 100.0), "speed_m_s"),
    (lambda: uav.PrintedLaw(1.0, 2.0, "fast", 4.0, 5.0), "v0_m_s"),
    (lambda: uav.PrintedLaw(np.ones(2), np.ones(3), 1.0, 1.0, 1.0), "b_m_s"),
    (lambda: GnssNoise(psd_prr_m2_s=math.nan), "psd_prr_m2_s"),
    (lambda: NavConfig(light_time="yes"), "light_time"),
    (lambda: NavConfig(integrity="on"), "integrity"),
    (lambda: SondeParams(p1_1_s=-0.1), "p1_1_s"),
    (lambda: SondeParams(wind_speed_m_s=(-1.0,) * 12), "wind_speed_m_s"),
    (lambda: ParamSpec("WP_SPEED", 1.0, 2.0, 400.0), "default"),
    (lambda: ParamSpec("WP_SPEED", 1.0, max=math.nan), "max"),
    (lambda: ParamSpec("wp_speed", 1.0), "name"),
])
def test_a_bad_value_is_one_line_naming_the_field(make, key):
    with pytest.raises(ParamError) as exc:
        make()
    msg = str(exc.value)
    assert "\n" not in msg and msg.startswith(f"{key}: expected "), msg


@pytest.mark.parametrize("cls", CLASSES, ids=lambda c: c.__name__)
def test_every_init_field_is_declared_with_a_doc(cls):
    init = [f.name for f in dataclasses.fields(cls) if f.init]
    d = docs(cls)
    assert list(d) == init and all(len(v) > 10 for v in d.values()), d


def test_stored_types():
    sp = SondeParams(ascent_rate_m_s=6)
    assert sp.ascent_rate_m_s == 6.0 and isinstance(sp.ascent_rate_m_s, float)
    assert isinstance(sp.wind_alt_m, tuple) and hash(sp) == hash(SondeParams(ascent_rate_m_s=6.0))
    assert uav.Hold(np.int64(3)).batch_shape == (3,) and type(uav.Hold((2.0, 1)).batch_shape[0]) is int
    wm = uav.WaypointMission(WP, 100)
    assert wm.speed_m_s.shape == (1,) and not wm.speed_m_s.flags.writeable
    assert all(not a.flags.writeable for a in wm.waypoints_rad_m) and isinstance(wm.turn_gain_1_s, float)
    law = uav.SinusoidalLaw(np.array([100.0, 110.0]), speed_amp_m_s=10)
    assert law.batch_shape == (2,) and law.speed_amp_m_s.shape == (2,) and not law.speed_amp_m_s.flags.writeable
    nav = NavConfig(ls_iterations=3)
    assert nav.ls_iterations == 3 and isinstance(nav.noise, GnssNoise) and isinstance(nav.el_mask_rad, float)
