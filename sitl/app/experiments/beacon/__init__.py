"""`skyfuse experiment beacon`: seed 002, a (moving) radio beacon located from >= 3 UAVs.

Batch mode of the SITL: the same components a
live run has, stepped in simulation time over one ``sitl.bus.InMemoryTransport``, drained
every epoch (1 s):

    UAV swarm (RK4, 0.01 s) -> GNSS receivers -> onboard EKFs    -> bus uav/<i>/nav (UavNav)
    beacon (RK4) -> range / Doppler at each UAV + the UAV's nav  -> bus uav/<i>/beacon/b1
    truth                                                        -> bus truth/{beacon,uav}/...
    ground station: ground_station.beacon.BeaconLocator  -> bus gs/estimate/beacon/b1
    scoring: subscribes to truth and gs/estimate only

Each Monte Carlo trial is one run id (``<base>-t<k>``) on the shared bus; the UAVs' filters
and the locator run all trials as one batch.  The production locator (PRODUCTION,
"consider": the UAVs' navigation errors as Schmidt states after an "inflate" acquisition,
ground_station/beacon/) publishes its Estimates on the bus and is scored from
there; the comparison locators on the same messages ("inflate": R + kappa J P_i J', kappa =
101; "inflate" with white UAV errors, kappa = 1; "ignore": the UAVs taken as exact; the
seed's position-only filter) are scored from their states (result.json
``inflate_vs_ignore``: every locator of LOCATORS, accounting for the UAVs' uncertainty
against ignoring it).  The centralised filter (ground_station.beacon.central) is then
replayed on the same receiver outputs and links, and the PCRB computed at the truth.

Geometry (``--geometry``; vehicles/uav/__init__.py says how the seed's laws are read):

* ``printed`` (default) -- the paper's example as printed: UAV-1..3 and the beacon fly the
  printed velocity laws (RK4, 0.01 s) from the printed start point (xi0, eta0, zeta0) =
  (2253549, 4507098, 3903261) m, which the paper gives for all four vehicles.  The paper's
  filter starts from the prior mean X(0)^ = M[X(0)] (no numbers printed); here the prior is
  N(M, P0) with M the printed point (and the printed law's velocity there) and
  P0 = diag(PRIOR_POS_SIGMA_M^2 I, PRIOR_VEL_SIGMA_M_S^2 I) (50 m, 5 m/s): the world draws each
  trial's true beacon start from N(M, P0_pos) (its velocity then follows the law) and the
  locator starts at M with P0 (``LocatorConfig(init="prior")``): the truth never enters the
  filter.  Doubts: the printed laws make every vehicle climb ~60 m/s (to 45-51 km at
  1000 s), four vehicles leaving one point is odd, and some digits are damaged -- but it is
  what is printed, and the only reading under which the paper's metre-level errors are
  possible.
* ``geodetic`` -- the realistic reading: the prose's geodetic start points (UAVs lat 45 / 45.1
  / 45.3, lon 30 / 30.1 / 30.3, h 3000 / 3100 / 3500 m; beacon lat 47.3, lon 31, 3200 m), every
  vehicle heading north at its printed v0 (100 / 110 / 110; 115) + 10 sin(0.02 t) m/s with
  climb 15 cos(0.01 t); the beacon is ~250 km from the UAVs and the locator starts blind
  (multilateration, ground_station/beacon/multilateration.py).

Cases: ``three_satellites`` (the paper's: three satellites on unperturbed Keplerian orbits,
vehicles.uav_nav.example_three_satellites) and ``constellation`` (the GPS almanac, every
satellite above 10 deg), both with --uavs UAVs; ``by_uav_count``: the constellation case
with 3, 5, 10 and 30 UAVs.  Printed geometry: the further UAVs fly printed-style laws with
coefficients spread over the printed ranges (vehicles.uav.printed_uav_law), from the
same start point.  Geodetic: the first three at the seed's start points, the others on a
sunflower pattern (golden-angle spiral) of radius 0.35 deg about (45.15 N, 30.15 E) at
3000-3500 m, heading north at 100-110 m/s.

Scoring (after the first 100 s, as in the paper): ``errors_m`` per axis of the PAPER's frame
(xi, eta, zeta) = (ECEF y, ECEF z, ECEF x) (the printed start point is
r (cos45 sin30, sin45, cos45 cos30): eta is the polar axis, AXIS_ECEF): the largest |error|
of each trial, their median over trials and their max, against the paper's 25 / 9 / 15 m;
``rmse_m`` the 3-D position RMSE over trials and epochs; ``pcrb_m`` the mean over the same
epochs of sqrt(trace) of the PCRB's beacon position block (``pcrb_axes_m``: per paper
axis, the RMS over the same epochs of the bound's standard deviation, against
``rmse_axes_m``) (at trial 0's truth when the beacon's start is drawn per trial; with the
prior's information at the start when there is one); ``anees`` the position NEES (3 dof) averaged over trials at each epoch, then over the
epochs, with the 99 % chi-square band of one epoch's average.

Writes DIR/result.json (strict JSON) and PNG figures.  Progress on stderr.

The package: ``constants``, ``world`` (truth tracks, prior, satellites, the world side epoch by
epoch), ``case`` (one case over the bus), ``scoring``, ``figures``, ``cli`` (the command's
options and the command); every public name of the experiment is here.
"""
from __future__ import annotations

from sitl.app.experiments.beacon.case import _Scorer, _bus_stats, _central, locator_config, run_case  # noqa: F401
from sitl.app.experiments.beacon.cli import BeaconOptions, _uav_counts, add_args, check_args, main, run, table  # noqa: F401
from sitl.app.experiments.beacon.constants import (_BLOCK, _BLOCK_ROWS, AXES, AXIS_ECEF, BEACON_ID,  # noqa: F401
                                                   CASES, CENTRAL_START_PRIOR_S, DT_S, FAULT_DEFAULTS, FIGURES,
                                                   GEOMETRIES, INTEGRITY_MODES, LOCATORS, MEASUREMENT_KEYS,
                                                   PAPER_ERRORS_M, PRIOR_POS_SIGMA_M, PRIOR_UPDATE_ITERATIONS,
                                                   PRIOR_VEL_SIGMA_M_S, PRODUCTION, SETTLE_S)
from sitl.app.experiments.beacon.figures import plot  # noqa: F401
from sitl.app.experiments.beacon.scoring import (_scores, _series, _truth3, integrity_summary,  # noqa: F401
                                                 pcrb_series, summarise_case, uav_nav_rmse)
from sitl.app.experiments.beacon.world import (beacon_prior, constellation_for, draw_beacon_starts,  # noqa: F401
                                               gnss_information, scenario, truth_tracks, uav_speeds, uav_starts,
                                               world_epochs)
