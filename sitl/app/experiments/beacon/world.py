"""The world of the beacon experiment: the UAVs' and the beacon's truth tracks of either geometry,
the printed geometry's prior, the satellites of a case, the UAVs' GNSS information, and the world
side of a case epoch by epoch (receiver and beacon-link measurements)."""
from __future__ import annotations

import math
import time

import numpy as np

from sitl.app.experiments.beacon.constants import (_BLOCK, _BLOCK_ROWS, DT_S, GEOMETRIES, PRIOR_POS_SIGMA_M,
                                                   PRIOR_VEL_SIGMA_M_S)


def uav_starts(n: int):
    """Geodetic geometry: (lat deg, lon deg, h m) of n UAVs: the seed's three, then a sunflower."""
    from vehicles.uav import EXAMPLE_UAV_START

    out = [tuple(s) for s in EXAMPLE_UAV_START[:n]]
    golden = math.pi * (3.0 - math.sqrt(5.0))
    m = n - 3
    for j in range(m):
        r = 0.35 * math.sqrt((j + 0.5) / m)
        th = j * golden
        out.append((45.15 + r * math.cos(th), 30.15 + r * math.sin(th), 3000.0 + 100.0 * (j % 6)))
    return out[:n]


def uav_speeds(n: int):
    """Geodetic geometry: mean speeds of n UAVs: the printed 100 / 110 / 110, then spread over 100..110."""
    from vehicles.uav import EXAMPLE_UAV_SPEED_M_S

    speeds = list(EXAMPLE_UAV_SPEED_M_S[:n])
    g = (math.sqrt(5.0) - 1.0) / 2.0
    speeds += [100.0 + 10.0 * (((j + 1) * g) % 1.0) for j in range(n - 3)]
    return speeds[:n]


def beacon_prior():
    """Printed geometry: the prior (mean (6,), covariance (6, 6)) of the beacon's ECEF [B, V_B]
    at t = 0: the printed point, the printed law's velocity there, P0 (module docstring)."""
    from vehicles import uav
    from vehicles import beacon

    m = uav.paper_to_ecef(uav.PRINTED_START_PAPER_M)
    v = uav.printed_velocity_ecef(0.0, m, beacon.printed_beacon_law(1))[0]
    cov = np.diag([PRIOR_POS_SIGMA_M ** 2] * 3 + [PRIOR_VEL_SIGMA_M_S ** 2] * 3)
    return np.concatenate([m, v]), cov


def draw_beacon_starts(rng, trials: int):
    """Printed geometry: each trial's true beacon start, drawn from the prior's position part."""
    m, cov = beacon_prior()
    return m[0:3] + rng.standard_normal((int(trials), 3)) @ np.linalg.cholesky(cov[0:3, 0:3]).T


def truth_tracks(n_uavs: int, duration_s: float, geometry: str = "printed", beacon_starts=None):
    """Truth at the epochs 0, 1, ... duration (RK4, 0.01 s): t (K,), U, V (K, N, 3), and B, VB:
    (K, 3) for one beacon shared by every trial, or (K, T, 3) for the printed geometry with
    ``beacon_starts`` (T, 3) (one beacon per trial from its own start)."""
    from vehicles import beacon
    from vehicles import uav

    if geometry not in GEOMETRIES:
        raise ValueError(f"geometry must be one of {GEOMETRIES}, got {geometry!r}")
    t = np.arange(0.0, float(duration_s) + 1e-9, DT_S)
    if geometry == "printed":
        sw = uav.printed_uav_swarm(n_uavs)
        bc = beacon.printed_beacon(beacon_starts)
        tu, tb = sw.track(t), bc.track(t)
        B, VB = tb.pos_ecef_m, tb.vel_ecef_m_s
        if beacon_starts is None:
            B, VB = B[:, 0], VB[:, 0]
        return t, tu.pos_ecef_m, tu.vel_ecef_m_s, B, VB
    if beacon_starts is not None:
        raise ValueError("beacon_starts: the geodetic geometry has one beacon start")
    if n_uavs == 3:
        sw = uav.example_uav_swarm()
    else:
        s = np.array(uav_starts(n_uavs))
        lat, lon = np.radians(s[:, 0]), np.radians(s[:, 1])
        law = uav.SinusoidalLaw(speed_mean_m_s=np.array(uav_speeds(n_uavs)), speed_amp_m_s=10.0,
                                speed_omega_rad_s=0.02, heading0_rad=0.0, climb_amp_m_s=15.0, climb_omega_rad_s=0.01)
        sw = uav.UavSwarm(law, lat, lon, s[:, 2])
    bc = beacon.example_beacon("seed")
    tu, tb = sw.track(t), bc.track(t)  # = step(t) epoch by epoch, in one compiled call each
    return t, tu.pos_ecef_m, tu.vel_ecef_m_s, tb.pos_ecef_m, tb.vel_ecef_m_s


def scenario(geometry: str, n_uavs: int, duration_s: float, trials: int, rng):
    """(tracks, prior) of one case: the printed geometry draws each trial's beacon start from
    the prior (rng) and returns the prior; the geodetic one has no prior (None)."""
    if geometry == "printed":
        return truth_tracks(n_uavs, duration_s, geometry, draw_beacon_starts(rng, trials)), beacon_prior()
    return truth_tracks(n_uavs, duration_s, geometry), None


def constellation_for(case: str, U0, duration_s: float):
    from sitl.gnss import orbits
    from vehicles import uav_nav

    if case == "three_satellites":
        return uav_nav.example_three_satellites(U0, uav_nav.EXAMPLE_T0_GPS_S, duration_s=duration_s)
    return orbits.gps_constellation()


def gnss_information(t_gps, U, V, constellation, config):
    """Each UAV's GNSS Fisher information H' R^-1 H at its true state (K, N, 6, 6), with the
    satellites' instantaneous states and the elevation mask at the true position."""
    from sitl import geodesy
    from sitl.gnss import orbits
    from vehicles.uav_nav import ClockFreePseudorangeDoppler

    K, N = U.shape[:2]
    out = np.empty((K, N, 6, 6))
    for k in range(K):
        sp, sv = orbits.sat_state_ecef(constellation, float(t_gps[k]))
        _, el, _ = geodesy.ecef_to_aer(U[k][:, None, :], sp[None])
        model = ClockFreePseudorangeDoppler(np.broadcast_to(sp, (N,) + sp.shape), np.broadcast_to(sv, (N,) + sv.shape),
                                            config.noise.var_pr_m2, config.noise.var_prr_m2_s2,
                                            el >= config.el_mask_rad)
        _, H = model.h_and_H(np.concatenate([U[k], V[k]], axis=-1))
        w = 1.0 / model.R_diag()
        out[k] = np.einsum("nki,nk,nkj->nij", H, w, H)
    return out


def world_epochs(tracks, const, trials, rng, nav_cfg, link_cfg, filter_states=True, clock=None):
    """The world side of run_case, epoch by epoch: yields (GnssEpoch, BeaconLinkMeasurement,
    the onboard filters' satellite states or None) for trials x UAVs.

    Computed in blocks of up to _BLOCK epochs: the receivers' geometry of a block's epochs in one
    call, then the receivers' and links' noise epoch by epoch (the random draws in the same
    order as stepping one epoch at a time), then the ephemeris the onboard filters compute
    from those receiver outputs (``filter_states``), again in one call: the same numbers as
    one epoch at a time (vehicles.uav_nav.truth_geometry, filter_sat_states).  clock(name,
    t0) is told the time spent ("uav_gnss_and_nav", "beacon_link")."""
    from vehicles import uav_nav
    from sitl.radio import beacon_link

    t, U, V, B, VB = tracks
    K, N = U.shape[:2]
    t_gps = uav_nav.EXAMPLE_T0_GPS_S + t
    tick = clock or (lambda name, t0: None)
    # epochs per block: up to _BLOCK, fewer for large trials x UAVs batches so that a block's
    # arrays stay small (<= _BLOCK_ROWS receivers x satellites x 3 doubles each)
    block = max(1, min(_BLOCK, _BLOCK_ROWS // max(1, int(trials) * N)))
    for k0 in range(0, K, block):
        blk = range(k0, min(k0 + block, K))
        t0 = time.perf_counter()
        geo = uav_nav.truth_geometry(t_gps[blk.start:blk.stop, None], U[blk.start:blk.stop], V[blk.start:blk.stop],
                                     const, nav_cfg)
        eps, links = [], []
        for j, k in enumerate(blk):
            eps.append(uav_nav.gnss_measure(rng, float(t_gps[k]), U[k], V[k], const, nav_cfg, trials_shape=(trials,),
                                            geometry=geo.at(j)))
            t2 = time.perf_counter()
            if B.ndim == 3:  # one beacon per trial: (T, 1, 3) against (N, 3) -> (T, N)
                links.append(beacon_link.measure(rng, U[k], V[k], B[k][:, None], VB[k][:, None], link_cfg))
            else:
                links.append(beacon_link.measure(rng, U[k], V[k], B[k], VB[k], link_cfg, trials_shape=(trials,)))
            tick("beacon_link", t2)
            t0 += time.perf_counter() - t2
        sat = uav_nav.filter_sat_states(eps, const, nav_cfg) if filter_states else None
        tick("uav_gnss_and_nav", t0)
        for j in range(len(blk)):
            yield eps[j], links[j], None if sat is None else (sat[0][j], sat[1][j])
