"""The beacon experiment's constants (the paper's error bands and axes, the prior, the cases, the
locators compared) and `skyfuse experiment beacon`'s options, declared once (sitl.params)."""
from __future__ import annotations

import dataclasses
from pathlib import Path

from sitl.app.args import OUTPUT_DIR
from sitl.params import add_flags, choice, default_of, from_text, integer, number, param, quiet_option, validate


PAPER_ERRORS_M = {"xi": 25.0, "eta": 9.0, "zeta": 15.0}
AXES = ("xi", "eta", "zeta")
#: ECEF component of each paper axis: xi = y, eta = z (polar), zeta = x.
AXIS_ECEF = {"xi": 1, "eta": 2, "zeta": 0}
GEOMETRIES = ("printed", "geodetic")
PRIOR_POS_SIGMA_M = 50.0  # printed geometry: sigma of the beacon's start about the printed point, per axis
PRIOR_VEL_SIGMA_M_S = 5.0  # ... and of the locator's prior velocity (the truth's is the law's, within mm/s)
CENTRAL_START_PRIOR_S = 50.0  # with a prior the centralised filter starts from the locator's estimate then
PRIOR_UPDATE_ITERATIONS = 5  # iterated EKF updates of the locators (and the centralised filter) with a prior: one
# linearisation at the prediction diverged in 2 of 10 sweep trials (seed 1: 3 UAVs trial 0 locked onto the
# mirror through the UAVs' plane at ~10 s, 10 UAVs trial 2 (start 131 m off, 2.6 sigma) collapsed to a wrong
# solution at ~6 s, err 137 m vs sigma 20 m); 5 Gauss-Newton relinearisations: none (max error 136 m, then < 12 m)
CASES = ("three_satellites", "constellation")
INTEGRITY_MODES = ("off", "on", "compare")


def _uav_counts(text: str) -> list[int]:
    import argparse

    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None
    if not values or any(v < 3 for v in values):
        raise argparse.ArgumentTypeError(f"expected comma-separated integers >= 3, got {text!r}")
    return values


@dataclasses.dataclass(frozen=True)
class BeaconOptions:
    """`skyfuse experiment beacon`'s options, declared once (sitl.params); run_case's fault
    defaults (FAULT_DEFAULTS) are read from here."""

    uavs: int = param(3, check=integer(lo=3, what="an integer >= 3 (three UAVs at least)"),
                      doc="UAVs of the two main cases", note=", as in the seed")
    duration: float = param(1000.0, check=number(0, lo_open=True), metavar="S",
                            doc="simulated time, s at 1 Hz; > 105 (errors are scored after the first 100 s)")
    seed: int = param(1, check=integer(lo=0), doc="seed of the numpy Generators")
    out: Path = param(Path("out/beacon"), check=OUTPUT_DIR, metavar="DIR", doc="output directory for result.json and PNG figures")
    trials: int = param(20, check=integer(lo=1), doc="Monte Carlo trials of the main cases")
    sweep_trials: int = param(5, check=integer(lo=1), doc="Monte Carlo trials of each by_uav_count run")
    uav_counts: list = param(default_factory=lambda: [3, 5, 10, 30], check=from_text(_uav_counts, show=lambda v: ",".join(map(str, v))),
                              metavar="N,N,...", doc="UAV counts of by_uav_count, GPS constellation")
    geometry: str = param("printed", check=choice(*GEOMETRIES),
                          doc="printed: the paper's laws and common start point as printed, the beacon's start drawn "
                              "about it and the locator started from that prior; geodetic: the prose's lat/lon start "
                              "points, northward flight, blind start")
    integrity: str = param("off", check=choice(*INTEGRITY_MODES),
                           doc="integrity monitors: on = the production locator per UAV link and the UAVs' onboard "
                               "filters per satellite; compare = each main case again, monitored, on the same data")
    range_step_m: float = param(0.0, check=number(), flag="--range-step", metavar="M",
                                doc="fault: a range step of M m on one UAV's beacon link from --fault-at",
                                note=": none")
    range_step_uav: int = param(2, check=integer(lo=1), metavar="I", doc="UAV number (1..--uavs) of the range step")
    pr_step_m: float = param(0.0, check=number(), flag="--pr-step", metavar="M",
                             doc="fault: a pseudorange step of M m on the first satellite UAV --pr-step-uav tracks at "
                                 "--fault-at", note=": none")
    pr_step_uav: int = param(1, check=integer(lo=1), metavar="I", doc="UAV number of the pseudorange step")
    fault_at_s: float = param(150.0, check=number(0), flag="--fault-at", metavar="S",
                              doc="start of the injected faults, s since the run's start")
    quiet: bool = quiet_option()

    __post_init__ = validate


def add_args(p) -> None:
    add_flags(p, BeaconOptions)


# measurement faults of run_case (0: none): a range step on one UAV's beacon link, a
# pseudorange step on one satellite (the first the UAV tracks at the fault's start) of one UAV
FAULT_DEFAULTS = {k: default_of(BeaconOptions, k) for k in ("range_step_m", "range_step_uav", "pr_step_m",
                                                             "pr_step_uav", "fault_at_s")}
SETTLE_S = 100.0
DT_S = 1.0
BEACON_ID = "b1"
#: the measurement links of run_case's bus_faults: the UAVs' beacon measurements to the ground station
MEASUREMENT_KEYS = (f"*/uav/*/beacon/{BEACON_ID}",)
FIGURES = ("beacon_errors.png", "beacon_rmse_vs_pcrb.png", "beacon_uav_count.png")
# locators on the same messages: name -> LocatorConfig overrides
PRODUCTION = "consider"  # the locator whose Estimates go on the bus (the first of run_case's locators)
_BLOCK = 64  # epochs whose world side (receiver geometry, filter ephemeris) is computed in one call
_BLOCK_ROWS = 4096  # at most this many epochs x trials x UAVs in one block
LOCATORS = {
    "consider": {"observer_uncertainty": "consider"},
    "inflate": {},
    "inflate_white": {"uav_error_corr_s": 0.0},
    "ignore": {"observer_uncertainty": "ignore"},
    "position_only": {"motion": "position"},
}
