"""The beacon experiment's constants: the paper's error bands and axes, the prior, the cases, the
run's epochs, the locators compared, and run_case's measurement-fault defaults."""
from __future__ import annotations

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

# measurement faults of run_case (0: none): a range step on one UAV's beacon link, a
# pseudorange step on one satellite (the first the UAV tracks at the fault's start) of one UAV
# (the command's fault options default to these: cli.BeaconOptions)
FAULT_DEFAULTS = {"range_step_m": 0.0, "range_step_uav": 2, "pr_step_m": 0.0, "pr_step_uav": 1, "fault_at_s": 150.0}
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
