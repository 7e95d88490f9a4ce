"""The ground station's beacon locator: a filter on an emitter from the ranges and Dopplers that N
UAVs measure to it, and the centralised filter it is measured against.

Design.  The decomposition of seed 002 (eqs 10-11): every UAV navigates on board and sends, with
each beacon measurement, its own estimate [U_i, V_i] and covariance P_i; the locator estimates the
beacon [B, V_B] from those messages alone, batched over Monte Carlo trials.  On the seed's
geometry (a beacon ~230 km from three nearly collinear UAVs) the ranges fix the distance from the
UAVs' line and the position along it to metres but the angle about it to km: an ECEF EKF
linearised a few km round that circle leaks the radial information into the weak direction
(measured: height sigma 500 m, error 20-50 km, NEES ~1e6).  A track that starts blind from a
line-like formation far from the beacon therefore runs in formation-cylindrical coordinates
[s, rho, phi, v_s, v_rho, v_phi] (``frame``), where the circle is a coordinate line, and is
published as the unscented moments of that Gaussian; any other track (a prior start, a formation
spread in two dimensions, a beacon near the formation) is a plain ECEF EKF.  Motion: constant
velocity, white acceleration q = 1 m^2/s^3 (``motion``).  The UAVs' navigation errors, correlated
over tens of seconds, enter as a consider term: "inflate" (R + kappa J P_i J', kappa = 1 + 2 tau /
dt) or, in the live ground station, "consider": Schmidt states per UAV slot, Gauss-Markov in each
UAV's whitened error, the cross-covariances carried by the filter (``update``, filters.schmidt);
a track's first ``acquire_s`` runs as "inflate".  The blind start (``multilateration``) solves a
short window by Levenberg-Marquardt with weak height and velocity priors and carries the mirror
through the UAVs' plane as a second hypothesis until a likelihood-ratio test (``init_resolve_llr``
150) decides, publishing the two-track mixture meanwhile.  An epoch whose UAVs span less than
``min_formation_sigmas`` (12) times their own position sigma gives no measurement (their plane is
noise).  Optional: an iterated update (filters.iekf), the integrity monitor per UAV link
(``integrity``), and a lag window (``lag_window_s``, 5 s) in which a late measurement re-runs the
epochs since its own.  Key figures (``skyfuse experiment beacon``, printed run, 20 trials, position
ANEES after 100 s, 99 % band 1.78-4.60): "consider" 2.60 / 2.63 (three satellites /
constellation; "inflate" 0.57 / 0.59), RMSE 15.2 / 10.3 m; on the seed geometry kappa = 1 gave
ANEES 223 / 5e4 against 4.5 / 3.2 at kappa = 101.  ``motion="position"`` keeps the seed's own
filter for comparison (``position_only``).

Modules: ``config`` (LocatorConfig), ``measurements`` (ObserverEpoch and the range / Doppler
model), ``frame`` (the cylindrical frame), ``motion``, ``update`` (the per-epoch step: EKF,
iterated, Schmidt), ``position_only``, ``multilateration`` (the blind start), ``step`` (one step of
stacked tracks), ``estimate`` (the published moments), ``integrity`` (the monitor adapter),
``locator`` (BeaconLocator, the bus component), ``central`` (CentralFilter and the PCRB).
numpy/scipy plus sitl (bus, geodesy, multilateration, integrity events) and filters; never
imports vehicles.
"""
from __future__ import annotations

from .central import CentralFilter, LinkEpoch, link_information, pcrb_central
from .config import INITS, INTEGRITY, MOTIONS, LocatorConfig
from .frame import Frame, cyl_to_ecef, ecef_to_cyl, formation_frame, ut_to_ecef
from .locator import BeaconLocator
from .measurements import ObserverEpoch, range_doppler_blocks, second_order_var
from .motion import uav_error_transition
from .multilateration import InitFix, init_fix, local_up
from .position_only import position_only_step
from .update import cyl_step

__all__ = [
    "LocatorConfig",
    "ObserverEpoch",
    "Frame",
    "formation_frame",
    "cyl_to_ecef",
    "ecef_to_cyl",
    "ut_to_ecef",
    "InitFix",
    "init_fix",
    "local_up",
    "uav_error_transition",
    "cyl_step",
    "position_only_step",
    "range_doppler_blocks",
    "second_order_var",
    "BeaconLocator",
    "CentralFilter",
    "LinkEpoch",
    "link_information",
    "pcrb_central",
    "MOTIONS",
    "INITS",
    "INTEGRITY",
]
