"""`skyfuse experiment sonde`: seed 004, radiosonde position from relayed GNSS fused with an
aerological radar, against each source alone, in batch mode over the in-memory bus.

The world (vehicles.sonde.SondeFlight, sitl.radio.radar.Radar, sitl.radio.relay.Relay)
publishes, per sonde and epoch, a `Truth`, a `SondeRelay` (empty during a GNSS outage or
out of range) and a `RadarMeasurement` (when the radar has a valid range) through an
`InMemoryTransport`; three `ground_station.sonde.SondeTracker`s (fused,
radar_only, relay_only) subscribe, and by default two more with the naive white radar-noise
treatment (fused_white, radar_only_white) for the consistency comparison. Each epoch:
publish, ``drain(t)``, ``tracker.step(t)`` (which publishes the Estimates), ``drain(t)``.
A scorer subscribed to truth/** and gs/estimate/** gathers the errors; nothing else reads
the truth.

Scenario (`SondeScenario`): a 2 h flight at 1 Hz from the default aerological station; the
GCPP (radar and relay ground receiver G) 300 m from the launch pad at a bearing of 140 deg,
i.e. across the surface wind (from 230 deg), so the launch happens in a strong side wind
for the radar's antenna; the default winter jet-stream profile scaled by 1.15 (67 m/s at
11 km) so that every sonde reaches 250 km ground range inside the 2 h (checked and
reported); angular auto-tracking lost from 30 s to 330 s after launch (a 5 min loss in
the side wind at launch: range only meanwhile); a 120 s GNSS outage (the relay delivers
nothing) from 3600 s. Monte Carlo trials draw everything independently (one SeedSequence
child per trial, split into flight, radar and relay streams), so a trial's numbers do not
depend on which other trials run beside it.

Trackers: the tracker's model is the world models' parameters (not their states): the sonde
model's kinematics (``kinematics="relaxed"``: the velocity relaxes with p1, k_v vertically, to a
wind the tracker estimates, driven by the gust a_g of eq 20 with rate p1 + p2 and std sigma_a; the
wind changing at the shear x the vertical speed, the shear Gauss-Markov in height with the std and
correlation height of ``wind_shear_statistics``, the wind profile between launch and burst), or ``kinematics="singer"`` (eq 20 as printed, the model
before the relaxed model: Singer with the rate p1 + p2 and the stationary acceleration std of the sonde
model, sigma_a sqrt((p1 + p2) / (2 p1 + p2))), the relay's oscillator, the radar's AR(1) errors. ``filter="auto"``: the EKF, and the UKF for a sonde-epoch whose position
uncertainty is large against its distance to the radar (the radar-only track's range-only
coast after launch).

Scoring (scoring-side truth: the Truth messages, the flight's ground range and the slant
range from the GCPP), over the epochs inside the operating radius (ground range < 250 km and
slant range <= 250 km: beyond, neither source measures and every mode coasts alike):
  * ``by_range_km``: 3-D position RMSE per mode in 25 km ground-range bins up to 250 km,
    pooled over trials, over the epochs where every mode has an estimate; with the same-data
    comparison of fused and relay-only (RMSE gain, per-trial MSE difference and its standard
    error over the trials);
  * ``during_radar_loss``, ``during_gnss_outage``: RMSE per mode inside the episodes;
  * ``anees``: NEES of the published [pos, vel] estimate and covariance (6 dof) averaged over
    the trials at each epoch while every trial is inside, against the two-sided 99 %
    chi-square band of one epoch's average (chi2(6 N)/N); reported as the time mean, the
    fraction of epochs inside the band and the per-epoch band; ``consistent`` = the time
    mean inside the band;
  * ``continuity``: the fused track has an estimate at every epoch of every trial (from its
    first one), and its largest gap;
  * ``seed_study`` (``--seeds N``): trial 0 of N seeds (each the flight of ``--seed S --trials 1``),
    fused / relay-only / radar-only RMSE per seed overall and in each episode, against the live-robustness
    targets (fused below relay-only in >= 95 % of the seeds and never above 1.5x it; in each outage
    no worse on average than the source left); ``acquire_s`` starts the trackers in flight (the
    suite's short variant picks the sonde up 300 s before the GNSS outage);
  * ``wall_s`` and where it went (world, publishing, bus delivery, trackers -- which include
    building and publishing their Estimates).
"""
from __future__ import annotations

import dataclasses
import functools
import itertools
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sitl.app.experiments.common import (measurement_faults, prepare_out, progress_printer, save_figure,
                                      strict)
from sitl.scenario import SondeSection
from sitl.app.args import OUTPUT_DIR
from sitl.params import (
    ParamError, add_flags, backend_option, choice, default_of, integer, number, optional, param, quiet_option,
    require, several, string, switch, validate,
)

MODES = ("fused", "radar_only", "relay_only")
WHITE_MODES = ("fused_white", "radar_only_white")
COLORS = {"fused": "C3", "radar_only": "C0", "relay_only": "C2", "fused_white": "C1", "radar_only_white": "C9"}
LABELS = {"fused": "fused (relay + radar)", "radar_only": "radar only", "relay_only": "relayed GNSS only",
          "fused_white": "fused, naive white radar noise", "radar_only_white": "radar only, naive white radar noise"}
RUN_ID = "seed004"
RADAR_ID = "arls1"
FIGURES = ("sonde_error_vs_time.png", "sonde_rmse_vs_range.png", "sonde_nees.png")
INTEGRITY = ("off", "on", "compare")
#: the measurement links of run_trials' bus_faults: the relayed GNSS and the radar, to the ground station
MEASUREMENT_KEYS = (f"{RUN_ID}/sonde/*/relay", f"{RUN_ID}/radar/*/sonde/*")
MONITORED = "_monitored"


def integrity_config():
    """The sonde trackers' integrity monitor (filters.integrity.IntegrityConfig)."""
    from filters.integrity import IntegrityConfig

    return IntegrityConfig(**SONDE_INTEGRITY)


# the trackers' monitor settings (see sitl/app/experiments/sonde.py's integrity note in the report)
SONDE_INTEGRITY = {"jump_sigma": 3.5, "window": 30, "window_alpha": 1e-4, "bias_alpha": None, "persist": 2,
                   "readmit_after": 10}


def _window(finite_end: bool = True):
    """A check: a (start, end) window of seconds since launch, 0 <= start < end, start finite (and
    end too unless ``finite_end`` is False: a fault that lasts to the end of the flight); stored
    as a tuple of floats."""
    what = "(start, end) with 0 <= start < end, s since launch"
    real = number(finite=False)

    def check(key, value):
        try:
            a, b = value
            a, b = real(key, a), real(key, b)
        except (TypeError, ValueError):  # not a pair of numbers (a ParamError is a ValueError)
            raise ParamError(key, f"expected {what}, got {value!r}") from None
        if not (math.isfinite(a) and (math.isfinite(b) or not finite_end) and 0 <= a < b):
            raise ParamError(key, f"expected {what}, got {value!r}")
        return (a, b)

    return check


def _relayed_satellite(key, value):
    """A check: "" (the first satellite delivered to trial 0 at the onset) or the id of a satellite
    of the relay's constellation (GPS + GLONASS)."""
    value = string()(key, value)
    if value:
        from sitl.gnss.orbits import default_constellation

        ids = [str(v) for v in default_constellation("GR").sat_id]
        if value not in ids:
            raise ParamError(key, f"expected a satellite of the relay's constellation (e.g. {ids[0]}), got {value!r}")
    return value


_POSITIVE = number(0, lo_open=True)


@dataclass(frozen=True)
class SondeScenario:
    """The seed 004 experiment (times relative to launch, seconds; SI units)."""

    duration_s: float = param(7200.0, check=_POSITIVE, doc="flight time simulated, s")
    dt_s: float = param(1.0, check=_POSITIVE, doc="epoch interval of the world, the bus and the trackers, s")
    wind_scale: float = param(default_of(SondeSection, "wind_scale"), check=_POSITIVE,
                              doc="factor on the default winter jet-stream wind profile (1.15: 58 -> 67 m/s at "
                                  "11 km, so that every sonde reaches 250 km ground range inside the 2 h)")
    gcpp_offset_m: float = param(300.0, check=_POSITIVE,
                                 doc="distance of the GCPP (the radar and the relay's ground receiver) from the "
                                     "launch pad, m")
    gcpp_bearing_deg: float = param(140.0, check=number(),
                                    doc="bearing of the GCPP from the launch pad, degrees from north (140: across "
                                        "the surface wind, from 230 deg)")
    radar_loss_s: tuple = param((30.0, 330.0), check=_window(),
                                doc="the radar's angular auto-tracking lost (range only) from start to end, s since "
                                    "launch (the side wind at launch)")
    gnss_outage_s: tuple = param((3600.0, 3720.0), check=_window(),
                                 doc="GNSS outage (the relay delivers nothing) from start to end, s since launch")
    acquire_s: float = param(0.0, check=number(0, what="a finite number >= 0 (below duration_s)"),
                             doc="the measurement links come up this long after launch (the trackers pick the sonde "
                                 "up in flight), s; below duration_s")
    bin_km: float = param(25.0, check=_POSITIVE, doc="width of the ground-range bins of the RMSE by range, km")
    max_range_km: float = param(250.0, check=_POSITIVE,
                                doc="operating radius: epochs are scored while the ground range is below it and the "
                                    "slant range from the GCPP within it, km")
    white_baseline: bool = param(True, check=switch(),
                                 doc="also run fused and radar-only trackers with the naive white radar-noise model "
                                     "(the NEES comparison)")
    filter: str = param("auto", check=choice("auto", "ekf", "ukf"),
                        doc="the trackers' filter: auto (the EKF, the UKF per sonde-epoch where the radar geometry "
                            "needs it), ekf or ukf")
    kinematics: str = param("relaxed", check=choice("relaxed", "singer"),
                            doc="the trackers' sonde kinematics (SondeTrackerParams.kinematics): relaxed (the sonde "
                                "model's structure: the velocity relaxes to a wind the tracker estimates) or singer "
                                "(eq 20 as printed)")
    integrity: str = param("off", check=choice(*INTEGRITY),
                           doc="the integrity monitor: off; on (every tracker monitored); compare (the three main "
                               "trackers plain, and each again with the monitor, <mode>_monitored, on the same "
                               "messages)")
    # measurement faults (sitl.measfault, world side; times since launch)
    relay_step_m: float = param(0.0, check=number(),
                                doc="fault: a clock step on one relayed satellite's pseudorange, m (0: none)")
    relay_step_sat: str = param("", check=_relayed_satellite,
                                doc="the satellite of the relay step (\"\": the first satellite delivered to trial 0 "
                                    "at the onset)")
    relay_step_s: tuple = param((1200.0, 1800.0), check=_window(finite_end=False),
                                doc="start and end of the relay step, s since launch")
    az_outlier_prob: float = param(0.0, check=number(0, what="a probability in [0, 1]"),
                                   doc="fault: a burst of heavy-tailed radar azimuth outliers (Student-t, 2 dof), "
                                       "probability per epoch in [0, 1] (0: none)")
    az_outlier_sigmas: float = param(10.0, check=_POSITIVE, doc="scale of the azimuth outliers, azimuth sigmas")
    az_outlier_s: tuple = param((900.0, 1000.0), check=_window(finite_end=False),
                                doc="start and end of the outlier burst, s since launch")
    az_step_rad: float = param(0.0, check=number(), doc="fault: a radar azimuth step, rad (0: none)")
    az_step_s: tuple = param((2400.0, 2700.0), check=_window(finite_end=False),
                             doc="start and end of the azimuth step, s since launch")

    def __post_init__(self):
        validate(self)
        require(self.acquire_s < self.duration_s, "acquire_s",
                f"expected a finite number in [0, duration_s), got {self.acquire_s!r}")
        require(self.az_outlier_prob <= 1.0, "az_outlier_prob",
                f"expected a probability in [0, 1], got {self.az_outlier_prob!r}")

    def filter_for(self, mode: str) -> str:
        """The trackers' filter: "auto" lets each tracker take the UKF for a sonde while its
        position uncertainty is large against its distance to the radar (a range-only coast
        near the radar, where the EKF's linearisation fails) and the EKF otherwise."""
        return self.filter

    @property
    def n_epochs(self) -> int:
        return round(self.duration_s / self.dt_s) + 1

    @property
    def modes(self) -> tuple:
        extra = tuple(m + MONITORED for m in MODES) if self.integrity == "compare" else ()
        return MODES + (WHITE_MODES if self.white_baseline else ()) + extra

    @property
    def has_faults(self) -> bool:
        return bool(self.relay_step_m or self.az_outlier_prob or self.az_step_rad)


# ------------------------------------------------------------------ the world


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


def tracker_params(scn: SondeScenario, label: str, backend=None):
    """The trackers' model: the world models' parameters (not their states)."""
    from ground_station.sonde import SondeTrackerParams
    from sitl.radio.radar import RadarParams
    from sitl.radio.relay import RelayParams

    sp, rp, gp = _sonde_params(scn), RadarParams(), RelayParams()
    monitored = label.endswith(MONITORED) or scn.integrity == "on"
    white = label.removesuffix(MONITORED).endswith("_white")
    beta = sp.p1_1_s + sp.p2_1_s
    g_h, g_len, g_v = wind_shear_statistics(sp)
    if scn.kinematics == "relaxed":  # the sonde model's own structure: its gust a_g, relaxation rates p1 and k_v
        s_h, s_v = sp.sigma_a_m_s2, sp.sigma_a_vertical_m_s2
    else:
        # the acceleration of the sonde model, a = (s / (s + p1)) a_g (the gust a_g seen through the
        # sonde's response p1; k_v vertically), has the stationary variance sigma_a^2 beta / (beta + p1):
        # the Singer model's sigma_a (eq 20 with the rate p1 + p2)
        s_h = sp.sigma_a_m_s2 * math.sqrt(beta / (beta + sp.p1_1_s))
        s_v = sp.sigma_a_vertical_m_s2 * math.sqrt(beta / (beta + sp.vertical_relax_rate_1_s))
    return SondeTrackerParams(
        mode=label.removesuffix(MONITORED).removesuffix("_white"), radar_noise="white" if white else "colored", filter=scn.filter_for(label),
        kinematics=scn.kinematics, velocity_relax_rate_horizontal_1_s=sp.p1_1_s,
        velocity_relax_rate_vertical_1_s=sp.vertical_relax_rate_1_s, wind_shear_sigma_horizontal_1_s=g_h,
        wind_shear_sigma_vertical_1_s=g_v, wind_shear_corr_height_m=g_len, descent_rate_sl_m_s=sp.descent_rate_sl_m_s,
        burst_alt_range_m=tuple(sp.burst_alt_range_m),
        accel_rate_1_s=beta, sigma_acc_horizontal_m_s2=s_h, sigma_acc_vertical_m_s2=s_v, osc_gamma_1_s=gp.osc_gamma_1_s,
        osc_sigma_m_s=2.0 * math.pi * gp.osc_sigma_hz * gp.osc_doppler_scale_m_s_per_rad_s,
        radar_sigma=tuple(rp.sigma), radar_gamma_1_s=tuple(rp.gamma_1_s), label=label,
        backend=None if backend in (None, "auto") else backend, integrity=integrity_config() if monitored else None)


class _Scorer:
    """Collects Truth and Estimate messages from the bus into arrays (trial, epoch)."""

    def __init__(self, modes, n_trials: int, n_epochs: int, t0: float, dt: float, sonde_index: dict):
        self.modes = {m: i for i, m in enumerate(modes)}
        self.t0, self.dt, self.index = t0, dt, sonde_index
        M, B, T = len(modes), n_trials, n_epochs
        self.truth_pos = np.full((B, T, 3), np.nan)
        self.truth_vel = np.full((B, T, 3), np.nan)
        self.pos = np.full((M, B, T, 3), np.nan)
        self.vel = np.full((M, B, T, 3), np.nan)
        self.cov = np.full((M, B, T, 6, 6), np.nan)
        self.count = np.zeros((M, B, T), dtype=np.int32)
        self.unexpected = 0
        self.k_now = None  # the epoch being stepped: an Estimate is scored there, as published (real time)

    def _k(self, t):
        return round((t - self.t0) / self.dt)

    def on_truth(self, key, msg):
        b = self.index.get(key.rsplit("/", 1)[-1])
        if b is None:
            self.unexpected += 1
            return
        k = self._k(msg.t_gps_s)
        self.truth_pos[b, k], self.truth_vel[b, k] = msg.pos_ecef_m, msg.vel_ecef_m_s

    def on_estimate(self, key, msg):
        b = self.index.get(key.rsplit("/", 1)[-1])
        m = self.modes.get(msg.mode)
        if b is None or m is None:
            self.unexpected += 1
            return
        k = self._k(msg.t_gps_s) if self.k_now is None else self.k_now
        self.pos[m, b, k], self.vel[m, b, k], self.cov[m, b, k] = msg.pos_ecef_m, msg.vel_ecef_m_s, msg.cov
        self.count[m, b, k] += 1


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


def run_trials(scn: SondeScenario, seed: int, trials, *, backend=None, progress=None, chunk: int = 300,
               modes=None, bus_faults=None, fault_seed: int | None = None, seeds=None) -> dict:
    """Simulate and track the given trial indices as one batch over the in-memory bus.

    modes: the trackers to run (default ``scn.modes``; a subset for timing -- ``score`` needs
    the three main ones). Returns the raw arrays (truth, estimates per mode, ground range,
    times) and timings.

    bus_faults: network faults on the MEASUREMENT links only (MEASUREMENT_KEYS: the
    relayed GNSS and the radar measurements), never the truth or the trackers' estimates: a
    list of FaultFilters (``sitl.netfault.KeyFaults``, ``LinkFault``) and/or KeyFaults rules
    ``(key_expr, spec)`` seeded with ``fault_seed`` (default: from ``seed``); times in the specs
    are seconds since launch.  Default none: no fault layer, the run it always was.  Estimates
    are scored at the epoch they are published (real time); ``out["bus_faults"]`` holds the
    injected truth summed over the links.

    seeds: one seed per trial (trial ``trials[b]`` of seed ``seeds[b]``, e.g. trial 0 of many seeds
    in one batch: the seed study); the sondes are then named by their place in the batch.
    """
    # the world and the ground station are imported here, not at module import: sitl must
    # not import vehicles or ground_station when it is itself imported
    from ground_station.sonde import SondeTracker
    from sitl.bus import InMemoryTransport, RadarMeasurement, SondeRelay, Truth
    from sitl.geodesy import geodetic_to_ecef

    trials = list(trials)
    B, T = len(trials), scn.n_epochs
    timing = dict.fromkeys(("world", "publish", "deliver", "trackers", "estimates_delivery"), 0.0)
    wall0 = time.perf_counter()
    w0 = time.perf_counter()
    t0, lat, lon, h, track, radar, relay = world(scn, seed, trials, backend=backend, seeds=seeds)
    timing["world"] += time.perf_counter() - w0

    fault_list, mfaults = measurement_faults(
        bus_faults, MEASUREMENT_KEYS, seed=(seed * 1009 + 8) if fault_seed is None else fault_seed, t0_gps_s=t0)
    bus = InMemoryTransport(start_t_gps_s=t0, faults=fault_list)
    ids = [f"s{i:04d}" for i in (trials if seeds is None else range(B))]
    index = {s: b for b, s in enumerate(ids)}
    modes = scn.modes if modes is None else tuple(modes)
    scorer = _Scorer(modes, B, T, t0, scn.dt_s, index)
    bus.subscribe(f"{RUN_ID}/truth/sonde/*", scorer.on_truth)
    bus.subscribe(f"{RUN_ID}/gs/estimate/sonde/*", scorer.on_estimate)
    events = []  # the integrity events on the bus: (t since launch, source, channel, event, statistic)
    bus.subscribe(f"{RUN_ID}/gs/integrity/*", lambda key, m: events.append(
        (m.t_gps_s - t0, m.source_id, m.channel, m.event, m.statistic)))
    # measurement faults (world side), one seeded stream for the batch
    from sitl.measfault import Fault, FaultInjector
    from sitl.radio.radar import RadarParams

    frng = np.random.default_rng(np.random.SeedSequence([seed, 3003]))
    az_faults = []
    if scn.az_outlier_prob:
        az_faults.append(Fault("outlier", 0, *scn.az_outlier_s, prob=scn.az_outlier_prob,
                               scale=scn.az_outlier_sigmas * RadarParams().sigma_az_rad, dof=2.0))
    if scn.az_step_rad:
        az_faults.append(Fault("step", 0, *scn.az_step_s, magnitude=scn.az_step_rad))
    az_inj = FaultInjector(az_faults, (B,), 1) if az_faults else None
    relay_inj, step_sat = None, None
    trackers = []
    for m in modes:
        tr = SondeTracker(RUN_ID, tracker_params(scn, m, backend), radar_id=RADAR_ID)
        tr.attach(bus)
        trackers.append(tr)
    k_relay = [f"{RUN_ID}/sonde/{s}/relay" for s in ids]
    k_radar = [f"{RUN_ID}/radar/{RADAR_ID}/sonde/{s}" for s in ids]
    k_truth = [f"{RUN_ID}/truth/sonde/{s}" for s in ids]
    seq = {"world": 0, "gcpp": 0, RADAR_ID: 0}
    examples = {"truth": None, "relay": None, "radar": None, "estimate": None}
    n_msgs = {"truth": 0, "relay": 0, "radar": 0}
    last_report = 0
    for c0 in range(0, T, chunk):
        c1 = min(T, c0 + chunk)
        w0 = time.perf_counter()
        rt = relay.track(track.t_gps_s[c0:c1], track.pos_ecef_m[c0:c1], track.vel_ecef_m_s[c0:c1])
        rmt = radar.track(track.t_gps_s[c0:c1], track.pos_ecef_m[c0:c1], track.vel_ecef_m_s[c0:c1])
        timing["world"] += time.perf_counter() - w0
        sat_id = rt.sat_id
        for j, k in enumerate(range(c0, c1)):
            t = float(track.t_gps_s[k])
            w0 = time.perf_counter()
            rv, rd, raz, rel, ra = (rmt.range_valid[j], rmt.slant_range_m[j], rmt.az_rad[j], rmt.el_rad[j],
                                    rmt.angles_valid[j])
            pr_all = rt.pseudorange_m[j]
            if scn.relay_step_m and relay_inj is None and t - t0 >= scn.relay_step_s[0]:
                ids = [str(v) for v in sat_id]
                if scn.relay_step_sat:
                    if scn.relay_step_sat not in ids:
                        raise ValueError(f"relay_step_sat: no satellite {scn.relay_step_sat!r} in the constellation")
                    step_sat = scn.relay_step_sat
                else:
                    seen = np.flatnonzero(rt.delivered[j, 0])
                    step_sat = ids[int(seen[0])] if seen.size else ids[0]
                relay_inj = FaultInjector([Fault("step", ids.index(step_sat), *scn.relay_step_s,
                                                 magnitude=scn.relay_step_m)], (B,), len(ids))
            if relay_inj is not None:
                pr_all, _ = relay_inj.step(frng, t - t0, pr_all)
            if az_inj is not None:
                az_f = az_inj.step(frng, t - t0, raz[:, None])[0][:, 0]
                raz = np.where(np.isfinite(az_f), np.mod(az_f, 2.0 * math.pi), az_f)
            vr, va, ve = rmt.var_range_m2[j], rmt.var_az_rad2[j], rmt.var_el_rad2[j]
            for b in range(B):
                msg = Truth(t_gps_s=t, source_id="world", seq=seq["world"], kind="sonde",
                            pos_ecef_m=track.pos_ecef_m[k, b], vel_ecef_m_s=track.vel_ecef_m_s[k, b])
                seq["world"] += 1
                bus.publish(k_truth[b], msg)
                examples["truth"] = msg
                n_msgs["truth"] += 1
                if t - t0 < scn.acquire_s:  # the measurement links are not up yet
                    continue
                d = rt.delivered[j, b]
                msg = SondeRelay(t_gps_s=t, source_id="gcpp", seq=seq["gcpp"], sat_ids=sat_id[d],
                                 pseudorange_m=pr_all[b][d], pseudo_doppler_m_s=rt.pseudo_doppler_m_s[j, b][d],
                                 var_pseudorange_m2=rt.var_pr_m2[j, b][d], var_pseudo_doppler_m2_s2=rt.var_prr_m2_s2[j, b][d],
                                 sat_pos_ecef_m=rt.sat_pos_ecef_m[j, b][d], sat_vel_ecef_m_s=rt.sat_vel_ecef_m_s[j, b][d],
                                 ground_pos_ecef_m=rt.ground_pos_ecef_m)
                seq["gcpp"] += 1
                bus.publish(k_relay[b], msg)
                if msg.n:
                    examples["relay"] = msg
                n_msgs["relay"] += 1
                if rv[b]:
                    msg = RadarMeasurement(t_gps_s=t, source_id=RADAR_ID, seq=seq[RADAR_ID],
                                           slant_range_m=float(rd[b]), az_rad=float(raz[b]), el_rad=float(rel[b]),
                                           var_range_m2=float(vr[b]), var_az_rad2=float(va[b]), var_el_rad2=float(ve[b]),
                                           angles_valid=bool(ra[b]), radar_pos_ecef_m=rmt.site_pos_ecef_m)
                    seq[RADAR_ID] += 1
                    bus.publish(k_radar[b], msg)
                    examples["radar"] = msg
                    n_msgs["radar"] += 1
            w1 = time.perf_counter()
            scorer.k_now = k
            bus.drain(t)
            w2 = time.perf_counter()
            for tr in trackers:
                est = tr.step(t)
            if est:
                examples["estimate"] = est[-1]
            w3 = time.perf_counter()
            bus.drain(t)
            w4 = time.perf_counter()
            timing["publish"] += w1 - w0
            timing["deliver"] += w2 - w1
            timing["trackers"] += w3 - w2
            timing["estimates_delivery"] += w4 - w3
        if progress and (c1 == T or c1 - last_report >= T // 10):
            last_report = c1
            progress(f"[sonde] {B} trial(s): {c1 - 1:>5d} / {T - 1} s simulated, "
                     f"{time.perf_counter() - wall0:6.1f} s wall")
    bus.close()
    return {
        "trials": trials, "t_gps_s": track.t_gps_s.copy(), "t0_gps_s": t0, "modes": modes,
        "ground_range_m": track.ground_range_m.T.copy(),  # (B, T), scoring-side truth
        "slant_range_m": np.linalg.norm(track.pos_ecef_m - geodetic_to_ecef(lat, lon, h), axis=-1).T.copy(),
        "alt_m": track.alt_m.T.copy(), "phase": track.phase.T.copy(), "burst_alt_m": track.burst_alt_m.copy(),
        "truth_pos": scorer.truth_pos, "truth_vel": scorer.truth_vel,
        "pos": scorer.pos, "vel": scorer.vel, "cov": scorer.cov, "count": scorer.count,
        "counters": {tr.label: tr.counters.as_dict() for tr in trackers},
        "bus": {"published": bus.stats.published, "delivered": bus.stats.total.delivered,
                "rejected": dict(bus.stats.total.rejected), "callback_errors": bus.stats.total.callback_errors,
                "messages_by_kind": {**n_msgs, "estimate": int(scorer.count.sum()), "integrity": len(events)}},
        "scorer_unexpected": scorer.unexpected,
        "integrity_events": events, "fault_relay_step_sat": step_sat,
        "bus_faults": None if mfaults is None else mfaults.totals(),
        "timing_s": timing, "wall_s": time.perf_counter() - wall0, "examples": examples,
    }


def bus_costs(examples: dict, rounds: int = 200) -> dict:
    """Per-message cost (us, best of 3 x ``rounds``) of the bus path for one example of each
    kind: building the message (the schema's validation), encoding, and decoding (which
    validates again) -- what every message of the run pays."""
    from sitl.bus import decode, encode

    out = {}
    for kind, msg in examples.items():
        if msg is None:
            continue
        cls = type(msg)
        kw = {f: getattr(msg, f) for f in ("t_gps_s", "source_id", "seq")}
        kw.update({s.name: getattr(msg, s.name) for s in cls.FIELDS})
        wire = encode(msg)
        best = {"build": math.inf, "encode": math.inf, "decode": math.inf}
        calls = (("build", lambda c=cls, k=kw: c(**k)), ("encode", lambda m=msg: encode(m)),
                 ("decode", lambda w=wire: decode(w)))
        for _ in range(3):
            for name, fn in calls:
                t0 = time.perf_counter()
                for _ in range(rounds):
                    fn()
                best[name] = min(best[name], (time.perf_counter() - t0) / rounds * 1e6)
        out[kind] = {**{k: round(v, 1) for k, v in best.items()}, "total_us": round(sum(best.values()), 1),
                     "bytes": len(wire)}
    return out


def _merge(parts: list[dict]) -> dict:
    """Concatenate run_trials outputs along the trial axis (same scenario)."""
    if len(parts) == 1:
        return parts[0]
    out = dict(parts[0])
    for k in ("ground_range_m", "slant_range_m", "alt_m", "phase", "burst_alt_m", "truth_pos", "truth_vel"):
        out[k] = np.concatenate([p[k] for p in parts], axis=0)
    for k in ("pos", "vel", "cov", "count"):
        out[k] = np.concatenate([p[k] for p in parts], axis=1)
    out["trials"] = [i for p in parts for i in p["trials"]]
    out["counters"] = {m: {c: sum(p["counters"][m][c] for p in parts) for c in parts[0]["counters"][m]}
                       for m in parts[0]["counters"]}
    bus = {"published": 0, "delivered": 0, "rejected": {}, "callback_errors": 0, "messages_by_kind": {}}
    for p in parts:
        for k in ("published", "delivered", "callback_errors"):
            bus[k] += p["bus"][k]
        for k, v in p["bus"]["rejected"].items():
            bus["rejected"][k] = bus["rejected"].get(k, 0) + v
        for k, v in p["bus"]["messages_by_kind"].items():
            bus["messages_by_kind"][k] = bus["messages_by_kind"].get(k, 0) + v
    out["bus"] = bus
    out["scorer_unexpected"] = sum(p["scorer_unexpected"] for p in parts)
    out["integrity_events"] = [e for p in parts for e in p["integrity_events"]]
    out["timing_s"] = {k: sum(p["timing_s"][k] for p in parts) for k in parts[0]["timing_s"]}
    out["wall_s"] = sum(p["wall_s"] for p in parts)
    if any(p.get("bus_faults") for p in parts):
        bf: dict = {}
        for p in parts:
            for k, v in (p.get("bus_faults") or {}).items():
                bf[k] = max(bf.get(k, 0), v) if k.endswith("_max") else bf.get(k, 0) + v
        out["bus_faults"] = bf
    return out


# ------------------------------------------------------------------ scoring


def _rmse(e2: np.ndarray):
    return float(np.sqrt(np.mean(e2))) if e2.size else None


def _paired(e2_a: np.ndarray, e2_b: np.ndarray, sel: np.ndarray):
    """Same-data comparison of two modes over the samples sel (B, T): the relative RMSE gain
    of a over b, 100 (1 - rmse_a / rmse_b) %, and the difference of the per-trial mean squared
    errors, mean and standard error over the trials (the trials are independent, the epochs
    of one trial are not)."""
    if not sel.any():
        return None
    per = [float(np.mean(e2_a[b][sel[b]] - e2_b[b][sel[b]])) for b in range(sel.shape[0]) if sel[b].any()]
    d = np.array(per)
    se = float(d.std(ddof=1) / math.sqrt(d.size)) if d.size > 1 else None
    ra, rb = math.sqrt(np.mean(e2_a[sel])), math.sqrt(np.mean(e2_b[sel]))
    return {"gain_percent": 100.0 * (1.0 - ra / rb), "mse_difference_m2": float(d.mean()),
            "mse_difference_stderr_m2": se, "trials": int(d.size)}


def score(raw: dict, scn: SondeScenario) -> dict:
    """The result document's numbers from run_trials' arrays."""
    from filters.metrics import chi2_bounds, nees

    modes = list(raw["modes"])
    t_rel = raw["t_gps_s"] - raw["t0_gps_s"]
    gr_km = raw["ground_range_m"] / 1e3  # (B, T)
    B = gr_km.shape[0]
    err = raw["pos"] - raw["truth_pos"][None]  # (M, B, T, 3)
    e2 = np.sum(err * err, axis=-1)  # (M, B, T)
    have = np.isfinite(e2)
    main = [modes.index(m) for m in MODES]
    common = np.all(have[main], axis=0)  # every main mode has an estimate
    # inside the operating radius: ground range below 250 km and slant range from the GCPP
    # within it too (beyond, neither radar nor relay measures: every mode coasts alike)
    inside = (gr_km < scn.max_range_km) & (raw["slant_range_m"] <= scn.max_range_km * 1e3)

    # RMSE by ground range
    edges = np.arange(0.0, scn.max_range_km + 1e-9, scn.bin_km)
    bins = []
    for lo, hi in itertools.pairwise(edges):
        sel = common & inside & (gr_km >= lo) & (gr_km < hi)
        row = {"range_km": float(lo), "rmse_m": {m: _rmse(e2[i][sel]) for i, m in enumerate(modes)},
               "n": int(sel.sum())}
        r = row["rmse_m"]
        row["fused_below_both"] = (None if r["fused"] is None else bool(r["fused"] < r["radar_only"]
                                                                        and r["fused"] < r["relay_only"]))
        row["fused_vs_relay_only"] = _paired(e2[modes.index("fused")], e2[modes.index("relay_only")], sel)
        bins.append(row)
    filled = [b for b in bins if b["n"] > 0]

    def episode(a, b):
        sel = common & (t_rel >= a)[None] & (t_rel < b)[None] & inside
        fi, ri, di = modes.index("fused"), modes.index("relay_only"), modes.index("radar_only")
        return {"window_s": [a, b], "n": int(sel.sum()),
                "rmse_m": {m: _rmse(e2[i][sel]) for i, m in enumerate(modes)},
                "fused_vs_relay_only": _paired(e2[fi], e2[ri], sel),
                "fused_vs_radar_only": _paired(e2[fi], e2[di], sel),
                "max_error_m": {m: (float(np.sqrt(e2[i][sel].max())) if sel.any() else None)
                                for i, m in enumerate(modes)}}

    # consistency: NEES of the published [pos, vel] estimate (6 dof), epochs with every trial inside
    x_err = np.concatenate([err, raw["vel"] - raw["truth_vel"][None]], axis=-1)  # (M, B, T, 6)
    ep = np.all(inside, axis=0) & np.all(common, axis=0)  # epochs (T,)
    lo, hi = chi2_bounds(6, B, 0.99)
    lo3, hi3 = chi2_bounds(3, B, 0.99)
    anees = {}
    for i, m in enumerate(modes):
        e_ok = ep & np.all(have[i], axis=0)
        if not e_ok.any():
            anees[m] = None
            continue
        nv = nees(x_err[i][:, e_ok], raw["cov"][i][:, e_ok])  # (B, Te)
        np3 = nees(err[i][:, e_ok], raw["cov"][i][:, e_ok, :3, :3])
        a, a3 = nv.mean(axis=0), np3.mean(axis=0)
        anees[m] = {"dof": 6, "mean": float(a.mean()), "median": float(np.median(a)),
                    "bounds_99_one_epoch": [lo, hi], "fraction_of_epochs_inside": float(np.mean((a >= lo) & (a <= hi))),
                    "consistent": bool(lo <= a.mean() <= hi),
                    "position_only": {"dof": 3, "mean": float(a3.mean()), "bounds_99_one_epoch": [lo3, hi3],
                                      "fraction_of_epochs_inside": float(np.mean((a3 >= lo3) & (a3 <= hi3)))},
                    "epochs": int(e_ok.sum()), "trials": B, "per_epoch": a, "per_epoch_t_s": t_rel[e_ok]}

    # continuity of the fused track: an estimate at every epoch from its first one
    fi = modes.index("fused")
    got = raw["count"][fi] > 0  # (B, T)
    first = np.argmax(got, axis=1)
    missing, max_gap = 0, 0.0
    for b in range(B):
        g = got[b, first[b]:]
        missing += int((~g).sum())
        idx = np.flatnonzero(got[b])
        if idx.size > 1:
            max_gap = max(max_gap, float(np.max(np.diff(idx)) * scn.dt_s))
    dup = int((raw["count"][fi] > 1).sum())
    first_s = (first * scn.dt_s).tolist()
    reached = np.any(gr_km >= scn.max_range_km, axis=1)
    t_reach = [float(t_rel[np.argmax(g >= scn.max_range_km)]) if r else None for g, r in zip(gr_km, reached)]
    out = {
        "by_range_km": bins,
        "fused_below_both_in_every_bin": bool(filled and all(b["fused_below_both"] for b in filled)),
        "during_radar_loss": episode(*scn.radar_loss_s),
        "during_gnss_outage": episode(*scn.gnss_outage_s),
        "anees": anees,
        "continuity": {"fused_estimate_every_epoch": bool(missing == 0 and dup == 0), "missing_epochs": missing,
                       "duplicate_epochs": dup, "max_gap_s": max_gap, "first_estimate_s": first_s},
        "flight": {"reached_max_range": [bool(r) for r in reached], "time_to_max_range_s": t_reach,
                   "all_reach_max_range": bool(reached.all()), "max_ground_range_km": gr_km.max(axis=1).tolist(),
                   "burst_alt_m": raw["burst_alt_m"].tolist(),
                   "burst_time_s": [float(t_rel[np.argmax(p == 1)]) if (p == 1).any() else None for p in raw["phase"]]},
    }
    out["overall_rmse_m"] = {m: _rmse(e2[i][common & inside]) for i, m in enumerate(modes)}
    with np.errstate(invalid="ignore"):
        w = (common & inside).sum(axis=0)
        out["series"] = {"t_s": t_rel, "rms_error_m": {m: np.where(w > 0, np.sqrt(
            np.where(common & inside, e2[i], 0.0).sum(axis=0) / np.maximum(w, 1)), np.nan) for i, m in enumerate(modes)}}
    return out


# ------------------------------------------------------------------ result.json and figures




def integrity_summary(raw: dict, sc: dict, scn: SondeScenario) -> dict | None:
    """The integrity monitor's part of the result: events on the bus by tracker and kind, by
    channel kind (relayed satellite / radar axis), the first ones, and with ``integrity="compare"``
    each main mode's RMSE without and with the monitor on the same messages."""
    if scn.integrity == "off":
        return None
    ev = raw.get("integrity_events", [])
    by_tracker: dict = {}
    by_channel: dict = {}
    for t, src, ch, kind, stat in ev:
        tr = src.removeprefix("sonde_tracker.").removesuffix(".integrity")
        d = by_tracker.setdefault(tr, {})
        d[kind] = d.get(kind, 0) + 1
        part = ch.split(".", 1)[1] if "." in ch else ch  # drop the sonde id
        key = f"{tr}:{part}:{kind}"
        by_channel[key] = by_channel.get(key, 0) + 1
    out = {"mode": scn.integrity, "config": dict(SONDE_INTEGRITY), "events": len(ev), "by_tracker": by_tracker,
           "by_channel": dict(sorted(by_channel.items(), key=lambda kv: -kv[1])[:40]),
           "first_events": [{"t_s": t, "source": src, "channel": ch, "event": kind,
                             "statistic": None if not math.isfinite(stat) else stat}
                            for t, src, ch, kind, stat in ev[:20]],
           "fault_relay_step_sat": raw.get("fault_relay_step_sat")}
    if scn.integrity == "compare":
        r = sc["overall_rmse_m"]
        out["overall_rmse_m"] = {m: {"without_monitor": r[m], "with_monitor": r.get(m + MONITORED)} for m in MODES}
    return out


def result_document(scn, seed: int, raw: dict, sc: dict, figures, wall_s: float, one_trial_wall_s) -> dict:
    anees = {m: ({k: v for k, v in a.items() if not k.startswith("per_epoch")} if a else None)
             for m, a in sc["anees"].items()}
    main = {m: anees[m] for m in MODES}
    comparison = None
    if scn.white_baseline:
        comparison = {
            "note": "naive: radar AR(1) errors taken as white (R = sigma^2); colored: the errors are states",
            "anees": {"colored": {m: anees[m] for m in ("fused", "radar_only")},
                      "white": {m.removesuffix("_white"): anees[m] for m in WHITE_MODES}},
            "overall_rmse_m": {"colored": {m: sc["overall_rmse_m"][m] for m in ("fused", "radar_only")},
                               "white": {m.removesuffix("_white"): sc["overall_rmse_m"][m] for m in WHITE_MODES}},
        }
    timing = dict(raw["timing_s"])
    nmsg = raw["bus"]["delivered"]
    costs = bus_costs(raw.get("examples", {}))
    kinds = raw["bus"]["messages_by_kind"]
    implied = sum(kinds.get(k, 0) * c["total_us"] for k, c in costs.items()) * 1e-6
    bus_s = timing["publish"] + timing["deliver"] + timing["estimates_delivery"]
    doc = {
        "experiment": "sonde", "schema": 1, "seed": seed, "trials": len(raw["trials"]),
        "scenario": dataclasses.asdict(scn), "epochs": scn.n_epochs,
        "by_range_km": sc["by_range_km"],
        "fused_below_both_in_every_bin": sc["fused_below_both_in_every_bin"],
        "during_radar_loss": sc["during_radar_loss"], "during_gnss_outage": sc["during_gnss_outage"],
        "anees": main, "radar_noise_comparison": comparison,
        "continuity": sc["continuity"], "flight": sc["flight"], "overall_rmse_m": sc["overall_rmse_m"],
        "tracker_counters": raw["counters"], "bus": raw["bus"],
        "integrity": integrity_summary(raw, sc, scn),
        "wall_s": wall_s, "wall_s_per_trial": wall_s / max(1, len(raw["trials"])),
        "one_trial_wall_s": one_trial_wall_s,
        "timing_s": {**timing, "bus_total": bus_s, "messages_delivered": nmsg,
                     "bus_s_per_message": bus_s / nmsg if nmsg else None},
        "bus_cost_per_message_us": costs,
        "bus_cost_implied_s": implied,
        "bus_cost_note": "build + encode + decode of every message of the run at the measured per-kind cost "
                         "(the Estimates are built and published inside the trackers' time)",
        "figures": [Path(f).name for f in figures],
    }
    return strict(doc)


def _shade(ax, scn):
    a, b = scn.radar_loss_s
    ax.axvspan(a, b, color="C0", alpha=0.12, lw=0, label=f"radar angle tracking lost ({a:g}-{b:g} s)")
    a, b = scn.gnss_outage_s
    ax.axvspan(a, b, color="C2", alpha=0.15, lw=0, label=f"GNSS outage ({a:g}-{b:g} s)")


def plot(raw: dict, sc: dict, scn: SondeScenario, seed: int, out: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    B = len(raw["trials"])
    filt = "EKF (UKF where needed)" if scn.filter == "auto" else scn.filter.upper()
    sub = f"seed 004, {B} trial(s), seed {seed}, {scn.duration_s:g} s at {1 / scn.dt_s:g} Hz, {filt}"
    files = []
    t = sc["series"]["t_s"]
    # a) error against time
    fig, ax = plt.subplots(figsize=(11, 6), constrained_layout=True)
    _shade(ax, scn)
    for m in ("radar_only", "relay_only", "fused"):  # fused last: on top of relay-only, which it hugs
        ax.plot(t, sc["series"]["rms_error_m"][m], color=COLORS[m], lw=1.0 if m != "fused" else 0.9,
                ls="-" if m != "fused" else (0, (4, 2)), label=LABELS[m])
    ax.set_yscale("log")
    ax.set_xlabel("time since launch, s")
    ax.set_ylabel("3-D position error, m (RMS over trials)")
    ax.set_xlim(0, scn.duration_s)
    ax.grid(alpha=0.3, which="both")
    ax2 = ax.twinx()
    gr = np.nanmean(raw["ground_range_m"], axis=0) / 1e3
    ax2.plot(t, gr, color="0.5", lw=0.8, ls="--", label="mean ground range (right axis)")
    ax2.set_ylabel("ground range, km")
    h1, l1 = ax.get_legend_handles_labels()
    h2, l2 = ax2.get_legend_handles_labels()
    ax.legend(h1 + h2, l1 + l2, loc="upper left", fontsize=8)
    ax.set_title(f"Radiosonde position error against time (epochs inside {scn.max_range_km:g} km)\n{sub}")
    files.append(save_figure(fig, out / FIGURES[0]))

    # b) RMSE against ground range, and the same-data gain of fused over relay-only
    fig, (ax, axg) = plt.subplots(2, 1, figsize=(10, 8), sharex=True, constrained_layout=True,
                                  gridspec_kw={"height_ratios": [2.2, 1]})
    bins = [b for b in sc["by_range_km"] if b["n"] > 0]
    centres = np.array([b["range_km"] + scn.bin_km / 2 for b in bins])
    order = [m for m in raw["modes"] if m in WHITE_MODES] + ["radar_only", "relay_only", "fused"]
    for m in order:
        y = np.array([np.nan if b["rmse_m"][m] is None else b["rmse_m"][m] for b in bins])
        white = m in WHITE_MODES
        ax.plot(centres, y, marker="s" if m == "fused" else "o", ms=4 if m == "fused" else 6,
                ls=":" if white else ("--" if m == "fused" else "-"), color=COLORS[m], label=LABELS[m],
                lw=1.0 if white else 1.6, zorder=5 if m == "fused" else 3)
        if m == "fused":
            for c, v in zip(centres, y):
                ax.annotate(f"{v:.2f}", (c, v), xytext=(5, -12), textcoords="offset points", ha="left",
                            fontsize=7, color=COLORS[m])
    ax.set_yscale("log")
    ax.set_ylabel("3-D position RMSE, m")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8, loc="center left")
    ax.set_title(f"Position RMSE against ground range ({scn.bin_km:g} km bins, all trials pooled)\n{sub}")
    gains, errs = [], []
    for b in bins:
        p = b.get("fused_vs_relay_only")
        r = b["rmse_m"]["relay_only"]
        if not p or not r:
            gains.append(np.nan)
            errs.append(0.0)
            continue
        gains.append(p["gain_percent"])
        se = p["mse_difference_stderr_m2"]
        errs.append(0.0 if se is None else 2.0 * 100.0 * se / (2.0 * r * r))  # 2 s.e., in RMSE %
    gains = np.array(gains)
    axg.bar(centres, gains, width=0.6 * scn.bin_km, color=np.where(gains > 0, "C3", "0.6"), alpha=0.8,
            yerr=errs, capsize=3, label="fused vs relay-only, same data (error bar: 2 standard errors over trials)")
    axg.axhline(0.0, color="k", lw=0.8)
    axg.set_yscale("symlog", linthresh=1.0)
    axg.set_ylabel("RMSE gain over\nrelay-only, %")
    axg.set_xlabel("ground range from the launch site, km (bin centres)")
    axg.set_xlim(0, scn.max_range_km)
    axg.grid(alpha=0.3, which="both")
    axg.legend(fontsize=8, loc="upper left")
    files.append(save_figure(fig, out / FIGURES[1]))

    # c) ANEES against time with the chi-square band
    fig, ax = plt.subplots(figsize=(11, 5.5), constrained_layout=True)
    _shade(ax, scn)
    band = None
    order = [m for m in raw["modes"] if m in WHITE_MODES] + ["radar_only", "relay_only", "fused"]
    for m in order:
        a = sc["anees"].get(m)
        if not a:
            continue
        ax.plot(a["per_epoch_t_s"], a["per_epoch"], color=COLORS[m], lw=0.7, ls=":" if m in WHITE_MODES else "-",
                label=f"{LABELS[m]} (mean {a['mean']:.2f}, {100 * a['fraction_of_epochs_inside']:.0f} % inside)")
        band = a["bounds_99_one_epoch"]
    if band:
        ax.axhspan(band[0], band[1], color="k", alpha=0.08, label=f"99 % band of one epoch ({band[0]:.2f}-{band[1]:.2f})")
        ax.axhline(6.0, color="k", lw=0.8)
    ax.set_yscale("log")
    ax.set_xlabel("time since launch, s")
    ax.set_ylabel("ANEES over trials, [pos, vel] (6 dof)")
    ax.set_xlim(0, scn.duration_s)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7, loc="upper right")
    ax.set_title(f"Consistency: average NEES over trials per epoch (while every trial is inside "
                 f"{scn.max_range_km:g} km)\n{sub}")
    files.append(save_figure(fig, out / FIGURES[2]))
    return files




def _paired_text(p) -> str:
    if not p:
        return "-"
    se = p["mse_difference_stderr_m2"]
    return (f"{p['gain_percent']:+.2f} %, {p['mse_difference_m2']:+.4g}"
            + (f" +- {se:.2g}" if se is not None else ""))


def summary_table(doc: dict) -> str:
    modes = list(MODES) + ([m for m in WHITE_MODES] if doc["radar_noise_comparison"] else [])
    head = (f"{'range km':>9} | " + " | ".join(f"{m:>16}" for m in modes)
            + f" | {'n':>7} | fused best | fused vs relay-only: RMSE gain, MSE diff +- s.e. (m^2)")
    rows = [f"position RMSE (m) by ground range, {doc['trials']} trials, seed {doc['seed']}", head, "-" * len(head)]
    for b in doc["by_range_km"]:
        if not b["n"]:
            continue
        vals = [("" if b["rmse_m"][m] is None else f"{b['rmse_m'][m]:.2f}") for m in MODES]
        extra = [f"{b['rmse_m'][m]:.2f}" for m in WHITE_MODES] if doc["radar_noise_comparison"] else []
        rows.append(f"{b['range_km']:>5.0f}-{b['range_km'] + doc['scenario']['bin_km']:<3.0f} | "
                    + " | ".join(f"{v:>16}" for v in vals + extra) + f" | {b['n']:>7d} | {b['fused_below_both']!s:>10} | "
                    + _paired_text(b["fused_vs_relay_only"]))
    for name in ("during_radar_loss", "during_gnss_outage"):
        e = doc[name]
        vals = ", ".join(f"{m} {e['rmse_m'][m]:.2f}" for m in MODES if e["rmse_m"][m] is not None)
        rows.append(f"{name} {e['window_s']} s: RMSE {vals} m (n={e['n']}); fused vs relay-only "
                    f"{_paired_text(e['fused_vs_relay_only'])}; vs radar-only {_paired_text(e['fused_vs_radar_only'])}")
    for m in modes:
        a = (doc["anees"] if m in MODES else
             doc["radar_noise_comparison"]["anees"]["white"]).get(m.removesuffix("_white") if m in WHITE_MODES else m)
        if a:
            rows.append(f"ANEES {m:<17} {a['mean']:8.3f}  (99 % one-epoch band {a['bounds_99_one_epoch'][0]:.3f}-"
                        f"{a['bounds_99_one_epoch'][1]:.3f}, {100 * a['fraction_of_epochs_inside']:.1f} % of "
                        f"{a['epochs']} epochs inside; position only {a['position_only']['mean']:.3f})")
    c = doc["continuity"]
    rows.append(f"fused continuity: estimate every epoch {c['fused_estimate_every_epoch']} (missing {c['missing_epochs']}, "
                f"max gap {c['max_gap_s']:g} s); fused below both in every bin: {doc['fused_below_both_in_every_bin']}")
    f = doc["flight"]
    rows.append(f"every flight reaches {doc['scenario']['max_range_km']:g} km: {f['all_reach_max_range']} "
                f"(at {', '.join('-' if x is None else f'{x:.0f}' for x in f['time_to_max_range_s'])} s)")
    tm = doc["timing_s"]
    rows.append(f"wall {doc['wall_s']:.1f} s ({doc['wall_s_per_trial']:.2f} s per trial): world {tm['world']:.1f}, "
                f"publish {tm['publish']:.1f}, bus delivery {tm['deliver']:.1f} + {tm['estimates_delivery']:.1f}, "
                f"trackers {tm['trackers']:.1f} s; bus {1e6 * (tm['bus_s_per_message'] or 0):.0f} us per message")
    ig = doc.get("integrity")
    if ig:
        rows.append(f"integrity monitor ({ig['mode']}): {ig['events']} events on the bus; by tracker "
                    + "; ".join(f"{t}: " + ", ".join(f"{k} {v}" for k, v in d.items()) for t, d in ig["by_tracker"].items()))
        if "overall_rmse_m" in ig:
            rows.append("RMSE without / with the monitor, same messages (m): "
                        + ", ".join(f"{m} {v['without_monitor']:.2f} / {v['with_monitor']:.2f}"
                                    for m, v in ig["overall_rmse_m"].items() if v["with_monitor"] is not None))
    bc = doc["bus_cost_per_message_us"]
    rows.append("bus path per message (build + encode + decode, us): "
                + ", ".join(f"{k} {v['total_us']:.0f}" for k, v in bc.items())
                + f"; for the {sum(doc['bus']['messages_by_kind'].values())} messages of this run: "
                  f"{doc['bus_cost_implied_s']:.1f} s of the {doc['wall_s']:.1f} s")
    return "\n".join(rows)


# ------------------------------------------------------------------ the seed study

#: the issue's targets: fused overall RMSE below relay-only's in at least this fraction of the seeds,
#: and never above this ratio of it; during each outage no worse on average than the source left
STUDY_MIN_FRACTION_BELOW_RELAY = 0.95
STUDY_MAX_RATIO_TO_RELAY = 1.5
STUDY_FIGURE = "sonde_seed_study.png"


def seed_study(scn: SondeScenario, seeds, *, backend=None, progress=None, batch: int = 10) -> dict:
    """Trial 0 of every seed in ``seeds`` (each the flight of ``experiment sonde --seed S --trials 1``),
    run in batches of ``batch`` sondes through the three main trackers, scored per seed: the 3-D
    position RMSE of fused, relay-only and radar-only over the flight inside the operating radius
    and inside each episode (radar angle loss, GNSS outage), and the issue's targets over the seeds:

      * fused overall RMSE below relay-only's in >= STUDY_MIN_FRACTION_BELOW_RELAY of the seeds and
        never above STUDY_MAX_RATIO_TO_RELAY x it;
      * during the GNSS outage the fused RMSE no worse on average than radar-only's (the source still
        there), during the radar angle loss no worse than relay-only's: "on average" both as the mean
        of the per-seed RMSEs and as the RMSE pooled over the seeds' epochs.
    """
    seeds = [int(v) for v in seeds]
    if not seeds:
        raise ValueError("seeds: at least one")
    scn = dataclasses.replace(scn, white_baseline=False)
    names = {"overall": None, "radar_loss": scn.radar_loss_s, "gnss_outage": scn.gnss_outage_s}
    per = {k: {m: [] for m in MODES} for k in names}
    sums = {k: {m: [0.0, 0] for m in MODES} for k in names}
    wall0 = time.perf_counter()
    for s0 in range(0, len(seeds), batch):
        part = seeds[s0:s0 + batch]
        prog = (lambda m, _p=part: progress(f"seeds {_p[0]}-{_p[-1]}: {m}")) if progress else None
        raw = run_trials(scn, part[0], [0] * len(part), backend=backend, progress=prog, modes=MODES, seeds=part)
        t_rel = raw["t_gps_s"] - raw["t0_gps_s"]
        e2 = np.sum((raw["pos"] - raw["truth_pos"][None]) ** 2, axis=-1)  # (M, B, T)
        common = np.all(np.isfinite(e2), axis=0)
        inside = (raw["ground_range_m"] < scn.max_range_km * 1e3) & (raw["slant_range_m"] <= scn.max_range_km * 1e3)
        for name, win in names.items():
            sel = common & inside
            if win is not None:
                sel = sel & ((t_rel >= win[0]) & (t_rel < win[1]))[None]
            for i, m in enumerate(raw["modes"]):
                for b in range(len(part)):
                    v = e2[i, b][sel[b]]
                    per[name][m].append(float(np.sqrt(v.mean())) if v.size else None)
                    sums[name][m][0] += float(v.sum())
                    sums[name][m][1] += int(v.size)
    wall = time.perf_counter() - wall0
    f, r, d = (per["overall"][m] for m in ("fused", "relay_only", "radar_only"))
    ratio = [a / b for a, b in zip(f, r)]
    below = [a < b for a, b in zip(f, r)]
    frac = sum(below) / len(below)
    worst = int(np.argmax(ratio))

    def episode(name, left):
        """None where no seed has epochs in the episode (e.g. before the links come up)."""
        if not sums[name]["fused"][1]:
            return {"window_s": list(names[name]), "source_left": left, "mean_rmse_m": None, "pooled_rmse_m": None,
                    "fused_no_worse_on_average": None, "seeds_fused_below_source_left": None}
        mean = {m: float(np.mean([v for v in per[name][m] if v is not None])) for m in MODES}
        pooled = {m: math.sqrt(sums[name][m][0] / sums[name][m][1]) for m in MODES}
        return {"window_s": list(names[name]), "source_left": left, "mean_rmse_m": mean, "pooled_rmse_m": pooled,
                "fused_no_worse_on_average": bool(mean["fused"] <= mean[left] and pooled["fused"] <= pooled[left]),
                "seeds_fused_below_source_left": sum(a < b for a, b in zip(per[name]["fused"], per[name][left])
                                                     if a is not None and b is not None)}

    gnss, loss = episode("gnss_outage", "radar_only"), episode("radar_loss", "relay_only")
    checks = {"fraction_fused_below_relay_only": frac >= STUDY_MIN_FRACTION_BELOW_RELAY,
              "worst_ratio_to_relay_only": ratio[worst] <= STUDY_MAX_RATIO_TO_RELAY,
              "gnss_outage_no_worse_than_radar_only": gnss["fused_no_worse_on_average"],
              "radar_loss_no_worse_than_relay_only": loss["fused_no_worse_on_average"]}
    checks = {k: v for k, v in checks.items() if v is not None}  # an episode outside the run: not judged
    return {
        "experiment": "sonde", "study": "seeds", "schema": 1, "seeds": seeds, "trial": 0,
        "scenario": dataclasses.asdict(scn),
        "per_seed": [{"seed": sd, **{f"{name}_rmse_m": {m: per[name][m][b] for m in MODES} for name in names},
                      "fused_to_relay_only": ratio[b], "fused_below_relay_only": below[b]}
                     for b, sd in enumerate(seeds)],
        "fraction_fused_below_relay_only": frac, "fraction_fused_below_radar_only": sum(
            a < b for a, b in zip(f, d)) / len(f),
        "worst_ratio_to_relay_only": {"ratio": ratio[worst], "seed": seeds[worst]},
        "median_ratio_to_relay_only": float(np.median(ratio)),
        "overall": {"mean_rmse_m": {m: float(np.mean(per["overall"][m])) for m in MODES},
                    "pooled_rmse_m": {m: math.sqrt(sums["overall"][m][0] / sums["overall"][m][1]) for m in MODES}},
        "during_gnss_outage": gnss, "during_radar_loss": loss,
        "targets": {"min_fraction_below_relay_only": STUDY_MIN_FRACTION_BELOW_RELAY,
                    "max_ratio_to_relay_only": STUDY_MAX_RATIO_TO_RELAY},
        "checks": checks, "pass": bool(all(checks.values())), "wall_s": wall,
    }


def plot_seed_study(doc: dict, out: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = doc["per_seed"]
    seeds = np.array([r["seed"] for r in rows])
    fig, ax = plt.subplots(3, 1, figsize=(12, 11), constrained_layout=True)
    x = np.arange(len(rows))
    sub = (f"seed 004, trial 0 of seeds {seeds[0]}-{seeds[-1]} ({len(rows)} flights), "
           f"{doc['scenario']['duration_s']:g} s, kinematics {doc['scenario']['kinematics']}")
    ratio = np.array([r["fused_to_relay_only"] for r in rows])
    ax[0].bar(x, ratio, color=np.where(ratio < 1.0, "C3", "0.5"))
    ax[0].axhline(1.0, color="k", lw=0.8)
    ax[0].axhline(doc["targets"]["max_ratio_to_relay_only"], color="k", ls="--", lw=0.8, label="the 1.5x limit")
    ax[0].set_ylabel("fused / relay-only\noverall RMSE")
    ax[0].set_title(f"Fused against relayed GNSS alone, per seed: {100 * doc['fraction_fused_below_relay_only']:.0f} % below "
                    f"(target >= {100 * doc['targets']['min_fraction_below_relay_only']:.0f} %), worst "
                    f"{doc['worst_ratio_to_relay_only']['ratio']:.2f} (seed {doc['worst_ratio_to_relay_only']['seed']}); "
                    f"{'PASS' if doc['pass'] else 'FAIL'}\n{sub}")
    ax[0].legend(fontsize=8)
    for a, name, title in ((ax[1], "gnss_outage", "GNSS outage (radar left)"),
                           (ax[2], "radar_loss", "radar angle tracking loss (relay left)")):
        e = doc["during_" + name]
        if e["mean_rmse_m"] is None:
            a.set_title(f"{title}: no epochs in this run")
            continue
        w = 0.28
        for j, m in enumerate(("fused", "relay_only", "radar_only")):
            a.bar(x + (j - 1) * w, [np.nan if r[f"{name}_rmse_m"][m] is None else r[f"{name}_rmse_m"][m] for r in rows],
                  width=w, color=COLORS[m], label=LABELS[m])
        a.set_yscale("log")
        a.set_ylabel("RMSE in the episode, m")
        a.set_title(f"{title} {e['window_s'][0]:g}-{e['window_s'][1]:g} s: mean over seeds "
                    + ", ".join(f"{m} {e['mean_rmse_m'][m]:.1f}" for m in MODES) + " m")
        a.legend(fontsize=8, ncol=3)
    for a in ax:
        a.set_xticks(x)
        a.set_xticklabels([str(s) for s in seeds], fontsize=6)
        a.grid(alpha=0.3, axis="y", which="both")
    ax[2].set_xlabel("seed")
    return save_figure(fig, out / STUDY_FIGURE)


def seed_study_table(doc: dict) -> str:
    c = doc["checks"]
    rows = [f"seed study: trial 0 of {len(doc['seeds'])} seeds ({doc['seeds'][0]}-{doc['seeds'][-1]}), "
            f"{doc['scenario']['duration_s']:g} s, kinematics {doc['scenario']['kinematics']}",
            f"{'seed':>5} | {'fused':>8} {'relay':>8} {'radar':>8} | {'ratio':>5} | gnss outage fused/relay/radar | "
            f"radar loss fused/relay/radar"]

    def fmt(v):
        return "-" if v is None else f"{v:.1f}"

    for r in doc["per_seed"]:
        o, g, lo = r["overall_rmse_m"], r["gnss_outage_rmse_m"], r["radar_loss_rmse_m"]
        rows.append(f"{r['seed']:>5} | {o['fused']:8.2f} {o['relay_only']:8.2f} {o['radar_only']:8.1f} | "
                    f"{r['fused_to_relay_only']:5.2f} | {fmt(g['fused'])} / {fmt(g['relay_only'])} / {fmt(g['radar_only'])}"
                    f" | {fmt(lo['fused'])} / {fmt(lo['relay_only'])} / {fmt(lo['radar_only'])}")
    w = doc["worst_ratio_to_relay_only"]
    rows.append(f"fused below relay-only in {100 * doc['fraction_fused_below_relay_only']:.0f} % of the seeds "
                f"({'ok' if c['fraction_fused_below_relay_only'] else 'FAIL'}, target >= "
                f"{100 * doc['targets']['min_fraction_below_relay_only']:.0f} %); worst ratio {w['ratio']:.2f} at seed "
                f"{w['seed']} ({'ok' if c['worst_ratio_to_relay_only'] else 'FAIL'}, limit "
                f"{doc['targets']['max_ratio_to_relay_only']:g}); median ratio {doc['median_ratio_to_relay_only']:.2f}")
    for name, key in (("GNSS outage", "during_gnss_outage"), ("radar loss", "during_radar_loss")):
        e = doc[key]
        if e["mean_rmse_m"] is None:
            rows.append(f"{name}: no epochs in this run")
            continue
        rows.append(f"{name}: mean RMSE " + ", ".join(f"{m} {e['mean_rmse_m'][m]:.1f}" for m in MODES)
                    + "; pooled " + ", ".join(f"{m} {e['pooled_rmse_m'][m]:.1f}" for m in MODES)
                    + f" m; fused no worse than {e['source_left']}: {e['fused_no_worse_on_average']}")
    rows.append(f"study {'PASS' if doc['pass'] else 'FAIL'} ({doc['wall_s']:.0f} s wall)")
    return "\n".join(rows)


# ------------------------------------------------------------------ the command


# ------------------------------------------------------------------ the command's options
SEED = 4  # the default seed of a run
FIRST_SEED = 1  # ... and the first seed of a seed study


def _scn(name, f=lambda v: v):
    return lambda: f(default_of(SondeScenario, name))  # the default a None option stands for


@dataclass(frozen=True)
class SondeOptions:
    """`skyfuse experiment sonde`'s options, declared once (sitl.params). A None option keeps
    SondeScenario's default (shown in --help)."""

    seed: int | None = param(None, check=optional(integer(lo=0)), doc="seed of the numpy SeedSequence",
                             default_help=f"default {SEED}; with --seeds the first seed, default {FIRST_SEED}")
    seeds: int | None = param(None, check=optional(integer(lo=1)), metavar="N",
                              doc="seed study: trial 0 of N seeds (--seed .. --seed + N - 1), each a '--trials 1' "
                                  "flight; fused vs relay-only vs radar-only per seed, overall and per outage, "
                                  "against the targets")
    kinematics: str | None = param(None, check=optional(choice("relaxed", "singer")),
                                   doc="the trackers' sonde motion model: relaxed (the velocity relaxes to a wind the "
                                       "tracker estimates, as in the sonde model) or singer (eq 20 as printed)",
                                   shown=_scn("kinematics"))
    out: Path = param(Path("out/sonde"), check=OUTPUT_DIR, metavar="DIR",
                      doc="output directory for result.json and PNG figures")
    trials: int = param(20, check=integer(lo=1), doc="Monte Carlo trials")
    duration: float = param(default_of(SondeScenario, "duration_s"), check=number(0, lo_open=True), metavar="S",
                            doc="flight time simulated, s at 1 Hz", note=": the 2 h flight to 250 km")
    filter: str = param(default_of(SondeScenario, "filter"), check=choice("auto", "ekf", "ukf"),
                        doc="the trackers' filter: auto = the EKF, and the UKF for a sonde while its position "
                            "uncertainty is large against its distance to the radar (a range-only coast near the "
                            "radar defeats the EKF's linearisation); or one of them throughout")
    no_white_baseline: bool = param(False, check=switch(),
                                    doc="skip the two extra trackers with the naive white radar-noise model "
                                        "(NEES comparison)")
    backend: str = backend_option("filter kernels and flight loop: compiled (numba) or plain numpy")
    integrity: str | None = param(None, check=optional(choice("off", "on", "compare")),
                                  doc="integrity monitor on the trackers: on, or compare (the three main trackers "
                                      "plain and again monitored, <mode>_monitored, on the same messages)",
                                  shown=_scn("integrity"))
    relay_step: float | None = param(None, check=optional(number()), metavar="M",
                                     doc="inject a satellite clock step of M metres on one relayed satellite's "
                                         "pseudorange")
    relay_step_sat: str | None = param(None, check=optional(string()), metavar="ID",
                                       doc="that satellite", default_help="default: the first delivered to trial 0 "
                                                                          "at the onset")
    relay_step_at: list | None = param(None, check=optional(several(number(0), 2)), metavar=("A", "B"),
                                       doc="its start and end, s since launch", shown=_scn("relay_step_s"))
    az_outliers: float | None = param(None, check=optional(number()), metavar="P",
                                      doc="radar azimuth outlier burst: probability per epoch (10-sigma Student-t, "
                                          "2 dof)")
    az_outlier_at: list | None = param(None, check=optional(several(number(0), 2)), metavar=("A", "B"),
                                       doc="the burst's start and end, s since launch", shown=_scn("az_outlier_s"))
    az_step_deg: float | None = param(None, check=optional(number()), metavar="D", doc="radar azimuth step, degrees")
    az_step_at: list | None = param(None, check=optional(several(number(0), 2)), metavar=("A", "B"),
                                    doc="the step's start and end, s since launch", shown=_scn("az_step_s"))
    quiet: bool = quiet_option()

    __post_init__ = validate


def add_args(p) -> None:
    add_flags(p, SondeOptions)


def scenario_from_args(args) -> SondeScenario:
    kw = {"white_baseline": not getattr(args, "no_white_baseline", False), "filter": getattr(args, "filter", default_of(SondeOptions, "filter")),
          "kinematics": getattr(args, "kinematics", None) or default_of(SondeScenario, "kinematics")}
    if getattr(args, "duration", None) is not None:
        kw["duration_s"] = float(args.duration)
    # the integrity options (flags --integrity, --relay-step M, --relay-step-sat ID, --relay-step-at A B,
    # --az-outliers P, --az-outlier-at A B, --az-step-deg D, --az-step-at A B; absent: the defaults)
    if getattr(args, "integrity", None) is not None:
        kw["integrity"] = args.integrity
    for flag, name, conv in (("relay_step", "relay_step_m", float), ("relay_step_sat", "relay_step_sat", str),
                             ("relay_step_at", "relay_step_s", tuple), ("az_outliers", "az_outlier_prob", float),
                             ("az_outlier_at", "az_outlier_s", tuple), ("az_step_at", "az_step_s", tuple)):
        v = getattr(args, flag, None)
        if v is not None:
            kw[name] = conv(v)
    if getattr(args, "az_step_deg", None) is not None:
        kw["az_step_rad"] = math.radians(float(args.az_step_deg))
    return SondeScenario(**kw)


def run(scn: SondeScenario, trials: int, seed: int, *, backend=None, progress=None, batch: int = 10) -> dict:
    """All trials, in batches of ``batch`` trials (the bus and the trackers carry a batch)."""
    parts = []
    for s in range(0, trials, batch):
        idx = list(range(s, min(trials, s + batch)))
        prog = (lambda m, _i=idx: progress(f"trials {_i[0]}-{_i[-1]}: {m}")) if progress else None
        parts.append(run_trials(scn, seed, idx, backend=backend, progress=prog))
    return _merge(parts)


def main(args) -> int:
    from sitl.app.args import UsageError

    try:
        scn = scenario_from_args(args)
    except ValueError as exc:
        raise UsageError(" ".join(str(exc).split())) from None
    out = prepare_out(Path(args.out))
    progress = progress_printer(args.quiet)
    backend = None if args.backend == "auto" else args.backend
    n_seeds = getattr(args, "seeds", None)
    if n_seeds is not None:  # the seed study: trial 0 of seeds --seed (default 1) .. + n - 1
        first = FIRST_SEED if args.seed is None else args.seed
        doc = strict(seed_study(scn, range(first, first + n_seeds), backend=backend, progress=progress))
        doc["figures"] = [plot_seed_study(doc, out).name]
        (out / "result.json").write_text(json.dumps(doc, indent=1, allow_nan=False))
        print(seed_study_table(doc))
        print("wrote " + ", ".join(str(p) for p in [out / "result.json", *(out / f for f in doc["figures"])]))
        return 0
    if args.seed is None:
        args.seed = SEED
    wall0 = time.perf_counter()
    raw = run(scn, args.trials, args.seed, backend=backend, progress=progress)
    sc = score(raw, scn)
    wall = time.perf_counter() - wall0
    one = raw["wall_s"] if args.trials == 1 else None
    figures = plot(raw, sc, scn, args.seed, out)
    doc = result_document(scn, args.seed, raw, sc, figures, wall, one)
    (out / "result.json").write_text(json.dumps(doc, indent=1, allow_nan=False))
    print(summary_table(doc))
    print("wrote " + ", ".join(str(p) for p in [out / "result.json", *figures]))
    return 0
