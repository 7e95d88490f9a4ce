"""The world of the sonde experiment: the per-trial random streams, the GCPP's site, the sonde
model's parameters and wind-shear statistics, and the simulated flights, radar and relay of a batch
of trials (not yet stepped)."""
from __future__ import annotations

import functools
import math

import numpy as np

from sitl.app.experiments.sonde.scenario import SondeScenario


def _trial_streams(seed: int, trials) -> list:
    """Per trial (flight, radar, relay) Generators: SeedSequence(seed) child i, split in three."""
    root = np.random.SeedSequence(seed)
    idx = list(trials)
    kids = root.spawn(max(idx) + 1)
    return [tuple(np.random.default_rng(s) for s in kids[i].spawn(3)) for i in idx]


def _sonde_params(scn: SondeScenario):
    from vehicles.sonde import SondeParams

    return SondeParams.with_wind_scale(scn.wind_scale)


def gcpp_site(scn: SondeScenario):
    """(lat, lon, h) of the GCPP: gcpp_offset_m from the launch pad at gcpp_bearing_deg."""
    from sitl.geodesy import ecef_to_geodetic, enu_to_ecef
    from vehicles import sonde
    DEFAULT_LAUNCH_H_M, DEFAULT_LAUNCH_LAT_RAD, DEFAULT_LAUNCH_LON_RAD = (
        sonde.DEFAULT_LAUNCH_H_M, sonde.DEFAULT_LAUNCH_LAT_RAD, sonde.DEFAULT_LAUNCH_LON_RAD)

    b = math.radians(scn.gcpp_bearing_deg)
    enu = np.array([scn.gcpp_offset_m * math.sin(b), scn.gcpp_offset_m * math.cos(b), 0.0])
    pos = enu_to_ecef(enu, DEFAULT_LAUNCH_LAT_RAD, DEFAULT_LAUNCH_LON_RAD, DEFAULT_LAUNCH_H_M)
    lat, lon, h = ecef_to_geodetic(pos)
    return float(lat), float(lon), float(h)


@functools.lru_cache(maxsize=8)
def wind_shear_statistics(sp) -> tuple:
    """(horizontal std (1/s), correlation height (m), vertical std (1/s)) of the shear of the wind a
    sonde of SondeParams ``sp`` meets, over the heights it flies through (the launch height to the
    middle of the burst range, 1 m steps, each height alike: it crosses each one on the way up and
    on the way down): the horizontal shear is d w(h) / dh of the mean wind profile (rms over the
    heights and both axes), its correlation height the 1/e point of its autocorrelation in height;
    vertically, the shear of the target vertical speed that the descent law (the tracker's known
    input) leaves: none in the sonde model (the target is the constant ascent rate, then the law
    itself; the burst's step is left to the manoeuvre hypothesis). These are the relaxed tracker's
    wind-shear Gauss-Markov parameters (in height: the wind then changes at shear x vertical speed,
    ~3x faster per second in the descent than in the 5 m/s ascent): the world model's parameters,
    summarised, not its state."""
    from vehicles import sonde

    top = 0.5 * (sp.burst_alt_range_m[0] + sp.burst_alt_range_m[1])
    h = np.arange(sonde.DEFAULT_LAUNCH_H_M, top + 1.0, 1.0)
    shear = np.diff(sp.wind_enu_m_s(h), axis=0)  # (n, 2), per 1 m
    n = shear.shape[0]
    f = np.fft.rfft(shear, 2 * n, axis=0)
    ac = np.fft.irfft(np.sum(f * np.conj(f), axis=1), 2 * n)[:n]
    below = np.flatnonzero(ac < math.exp(-1.0) * ac[0]) if ac[0] > 0.0 else np.array([n])  # (a constant wind: no shear)
    corr = float(below[0]) if below.size else float(n)
    return float(np.sqrt(np.mean(shear**2))), max(corr, 1.0), 0.0


def _streams(seed: int, trials, seeds=None) -> list:
    """The per-trial Generators: trials of one seed, or (``seeds``, one per trial) trial
    ``trials[b]`` of seed ``seeds[b]`` -- the same flight as that seed's own run."""
    if seeds is None:
        return _trial_streams(seed, trials)
    seeds = list(seeds)
    if len(seeds) != len(trials):
        raise ValueError(f"seeds: one per trial ({len(trials)}), got {len(seeds)}")
    return [_trial_streams(s, [i])[0] for s, i in zip(seeds, trials)]


def world(scn: SondeScenario, seed: int, trials, *, backend=None, seeds=None):
    """The world of the given trials: (t0, GCPP lat, lon, h, the simulated flights (SondeTrack),
    the Radar and the Relay, not yet stepped). ``seeds``: one seed per trial (see _streams)."""
    from sitl.gnss.orbits import DEFAULT_TOA_GPS_S, default_constellation
    from sitl.radio.radar import Radar, RadarParams
    from sitl.radio.relay import Relay, RelayParams
    from vehicles.sonde import SondeFlight

    trials = list(trials)
    B, T = len(trials), scn.n_epochs
    streams = _streams(seed, trials, seeds)
    t0 = DEFAULT_TOA_GPS_S
    lat, lon, h = gcpp_site(scn)
    flight = SondeFlight([s[0] for s in streams], params=_sonde_params(scn), t0_gps_s=t0, dt_s=scn.dt_s,
                         backend="numba" if backend == "numba" else ("numpy" if backend == "numpy" else "auto"))
    track = flight.simulate(T - 1)
    radar = Radar([s[1] for s in streams], site_lat_rad=lat, site_lon_rad=lon, site_h_m=h,
                  params=RadarParams(loss_schedule=((t0 + scn.radar_loss_s[0], t0 + scn.radar_loss_s[1]),)),
                  batch_shape=(B,))
    relay = Relay([s[2] for s in streams], default_constellation("GR"), ground_lat_rad=lat, ground_lon_rad=lon,
                  ground_h_m=h, params=RelayParams(outage_schedule=((t0 + scn.gnss_outage_s[0],
                                                                    t0 + scn.gnss_outage_s[1]),)),
                  batch_shape=(B,))
    return t0, lat, lon, h, track, radar, relay
