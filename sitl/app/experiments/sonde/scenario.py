"""The seed 004 experiment's scenario (`SondeScenario`, every field declared with its check and
doc), its trackers' names and the integrity monitor's settings."""
from __future__ import annotations

import math
from dataclasses import dataclass

from sitl.params import ParamError, choice, default_of, number, param, require, string, switch, validate
from sitl.scenario import SondeSection


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


# the trackers' monitor settings (see the sonde experiment's integrity note in the report)
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
