"""UAV kinematics (seed 002): truth trajectories integrated by RK4, batched over vehicles.

State and ODE
-------------
Each vehicle's kinematic state is ``y = [lat_rad, lon_rad, h_m, heading_rad]`` (geodetic
WGS-84 latitude, longitude, ellipsoidal height; heading clockwise from north).  A guidance
law gives, at time t, the 3-D speed v, the climb rate v_u and the heading rate; then

    v_h   = sqrt(v^2 - v_u^2),   v_e = v_h sin(psi),   v_n = v_h cos(psi)
    lat'  = v_n / (M(lat) + h),  lon' = v_e / ((N(lat) + h) cos lat),  h' = v_u,
    psi'  = heading rate,

M, N the meridian and prime-vertical radii of curvature.  The ECEF velocity is the exact
time derivative of geodetic_to_ecef(lat, lon, h): v_ecef = R_enu' [v_e, v_n, v_u]
(dX/dlat = (M + h) north, dX/dlon = (N + h) cos(lat) east, dX/dh = up).  Integrating in
geodetic coordinates keeps the law in the local frame (speed, heading, climb) without an
ECEF -> geodetic iteration at every RK4 stage.  Singular at the poles (cos lat = 0).

The state arrays carry leading batch axes (vehicles, or anything the law's parameters
broadcast to); every vehicle of a swarm is advanced by one vectorised RK4 step.

Guidance laws
-------------
* :class:`SinusoidalLaw` -- the seed 002 example's character: speed
  ``v0 + a sin(w_v t + phi_v)``, climb ``c cos(w_c t + phi_c)``, heading
  ``psi0 + A sin(w_psi t + phi_psi)`` (slow sinusoidal variation, periods ~300-600 s).
* :class:`WaypointMission` -- fly a list of geodetic waypoints at a commanded speed with a
  bounded turn rate and climb rate (the mode a MAVLink mission upload drives).
* :class:`LegsAndTurns` -- straight legs and constant-rate turns on a time schedule.
* :class:`Racetrack` -- a clockwise holding pattern about a fixed centre held by guidance (an
  autopilot's loiter mode): a racetrack, or a circle (:meth:`Racetrack.orbit_through`: each
  vehicle's circle through its start point).
* :class:`Hold` -- a static vehicle (speed 0).
* :class:`PrintedLaw` -- the seed's velocity laws as printed, an ODE of the ECEF position
  itself (state [x, y, z], no geodetic state), integrated by :func:`propagate_printed`
  (RK4) and stepped by :class:`PrintedSwarm`.

How the seed's laws are read (seed 002, the example section "Пример", OCR lines ~426-498)
------------------------------------------------------------------------------------------
The paper prints, for UAV-1..3 and the beacon, the velocity in its Earth-fixed frame
(xi, eta, zeta) as a function of eta and t (r(t) = 6.374e6 + 1500 sin(w_r t),
c = sqrt(1 - eta^2 / r^2)):

    V_xi   = -(a + 0.5 sin 0.02t) eta / r + b cos(w' t) c
    V_eta  = (v0 + 10 sin 0.02t) c + 15 cos(0.01t) eta / r
    V_zeta = (sqrt 3 / 2) [ -(d + sin 0.02t) eta / r + e cos(w' t) c ]

with (a, b, v0, d, e, w', w_r) = UAV-1 (5, 7.5, 100, 10, 15, 0.01, 0.01), UAV-2 (10, 5.5,
110, 10, 15, 0.01, 0.01), UAV-3 (15, 6.5, 110, 20, 19, 0.01, 0.01), beacon (12, 8.5, 115,
25, 17, 0.02, 0.02) (:data:`PRINTED_COEFFS`; the OCR's 5.5, 6.5 and 19 are damaged
digits).  The printed start point (xi0, eta0, zeta0) = (2253549, 4507098, 3903261) m is the
SAME for the three UAVs and the beacon; it is r (cos45 sin30, sin45, cos45 cos30) with
r = 6371 km + 3000 m, i.e. latitude 45, longitude 30 on a sphere, so that

    xi = ECEF y,  eta = ECEF z (the polar axis),  zeta = ECEF x     (:func:`paper_to_ecef`).

Two readings are provided:

* "printed" (:class:`PrintedLaw`, :class:`PrintedSwarm`): the laws exactly as printed,
  integrated by RK4 at 0.01 s in ECEF (the law evaluated in the paper's axes) from the
  printed common start point.  Doubts, stated: the vehicles then climb ~60 m/s (45-51 km
  of height at 1000 s) -- the eta component carries the speed v0 while the xi / zeta
  components carry a tenth of it (a, d ~ v0 / 10), so the velocity is not horizontal;
  all four vehicles (beacon included) leave the same point; some digits are damaged.
  It is what is printed, and the only reading under which the paper's metre-level errors
  are possible (every reading with separate start points leaves the beacon ~250 km away).
* "geodetic" (:func:`example_uav_law`, :data:`EXAMPLE_UAV_START`): the prose's geodetic
  start points (the OCR says longitude 30 / 30.1 / 30.3, latitude 45 / 45.1 / 45.3,
  heights 3000 / 3100 / 3500 m) and the laws' physical content: the V_eta law is exactly
  the polar component of a northward flight at speed v0 + 10 sin(0.02 t) with climb
  15 cos(0.01 t) (north = (.., .., cos lat), up = (.., .., sin lat)), and the printed r(t)
  is the matching altitude h0 + 1500 sin(0.01 t).  So each vehicle flies north at its own
  v0 (100 / 110 / 110 m/s; beacon 115): the formation is not rigid.

SI units, radians inside; no randomness, no clocks: time is the simulation time t_s.

Modules: laws (the open-loop laws), guidance (the holding pattern and the waypoint mission),
kinematics (state, ODE, RK4, truth), kernels (the compiled integrator), swarm (the stepped
swarm, the seed's UAVs), printed (the printed laws), values and geometry (what they share).
"""
from __future__ import annotations

from .geometry import eta_axis_heading_rad, wrap_pi
from .guidance import Racetrack, WaypointMission
from .kinematics import KinematicState, VehicleTruth, geodetic_rates, initial_state, propagate, rk4_step, truth
from .laws import Hold, LegsAndTurns, SinusoidalLaw
from .printed import (PRINTED_COEFFS, PRINTED_START_PAPER_M, PrintedLaw, PrintedSwarm, ecef_to_paper, paper_to_ecef,
                      printed_uav_law, printed_uav_swarm, printed_velocity_ecef, propagate_printed)
from .swarm import EXAMPLE_UAV_SPEED_M_S, EXAMPLE_UAV_START, KinematicSwarm, UavSwarm, example_uav_law, example_uav_swarm

__all__ = [
    "SinusoidalLaw",
    "WaypointMission",
    "LegsAndTurns",
    "Racetrack",
    "Hold",
    "KinematicState",
    "VehicleTruth",
    "KinematicSwarm",
    "UavSwarm",
    "geodetic_rates",
    "rk4_step",
    "propagate",
    "initial_state",
    "truth",
    "eta_axis_heading_rad",
    "example_uav_law",
    "example_uav_swarm",
    "EXAMPLE_UAV_START",
    "EXAMPLE_UAV_SPEED_M_S",
    "PRINTED_START_PAPER_M",
    "PRINTED_COEFFS",
    "PrintedLaw",
    "PrintedSwarm",
    "paper_to_ecef",
    "ecef_to_paper",
    "printed_velocity_ecef",
    "propagate_printed",
    "printed_uav_law",
    "printed_uav_swarm",
    "wrap_pi",
]
