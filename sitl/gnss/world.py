"""The GNSS world: a receiver trajectory -> L1 observations of GPS + GLONASS (seed 000).

Glue between the orbit, light-time, atmosphere, clock and receiver models:

* :func:`observe` -- one epoch.  Light-time geometry (``ranging.light_time_geometry``:
  Earth rotation during the flight, exact range rate), the elevation of every satellite
  above the receiver's *geodetic* horizon (``geodesy.ecef_to_aer`` with the satellite
  at emission expressed in the reception-time ECEF frame, ``Geometry.sat_pos_ecef_m``),
  the per-satellite L1 carriers (GPS 1575.42 MHz, GLONASS FDMA 1602 + k 0.5625 MHz)
  and GPS flags of the constellation, then ``Receiver.step`` (noise, mask, atmosphere,
  ambiguities, slips).
* :func:`simulate_receiver` -- a whole trajectory: the receiver clock follows the
  seed 000 two-state model (``ClockModel``, exact discretisation for any step), and
  every epoch goes through :func:`observe`.  Returns an :class:`ObservationTrack`
  (epochs stacked on a leading axis T) that also keeps the truth needed for scoring.
* :func:`geometry_track` -- the truth geometry (light time, range rate, geodetic and
  geocentric elevations) of one trajectory shared by any number of receivers, computed a
  block of epochs per call and handed out epoch by epoch: memory stays flat in the run
  length and the per-call overhead of the 55-satellite evaluation is paid once per block.
  ``Receiver.step`` on each epoch's slice then gives what :func:`observe` gives.
* :func:`ephemeris_for_filter` -- what a receiver's estimator may use: the satellite
  states at the transit time *measured* by its pseudorange, pr / c (optionally less
  its own clock-bias estimate), masked to the tracked satellites.  No truth enters.

Shapes: the satellites sit on a fixed last axis S (the constellation order, whether
visible or not; untracked entries are NaN); the leading batch axes (...) are trials.
Times are true GPS seconds of reception.  SI units; randomness only from the passed
``numpy.random.Generator``.
"""
from __future__ import annotations

from dataclasses import dataclass, fields
from typing import NamedTuple

import numpy as np

from filters.params import array
from sitl.constants import C_M_S
from sitl.geodesy import ecef_to_aer, geocentric_elevation_rad
from sitl.gnss.clock import ClockModel
from sitl.gnss.orbits import Constellation
from sitl.gnss.ranging import (
    Geometry,
    _check_constellation,
    finite_vec3,
    light_time_geometry,
    sat_state_at_reception_frame,
)
from sitl.gnss.receiver import Observation, Receiver, ReceiverConfig

__all__ = [
    "EpochGeometry",
    "elevation_grid",
    "geometry_track",
    "look_angles",
    "observe",
    "ObservationTrack",
    "simulate_receiver",
    "ephemeris_for_filter",
    "visible_count",
    "NOMINAL_TAU_S",
]

_FINITE = array()  # a function argument of finite numbers, any shape (a read-only float copy)

#: Transit time put in for untracked satellites before evaluating the ephemeris (their
#: output is NaN afterwards); any value keeps ``sat_state_at_reception_frame`` happy.
NOMINAL_TAU_S = 0.075


# ---------------------------------------------------------------------------
# validation helpers
# ---------------------------------------------------------------------------

def _check_rng(rng) -> np.random.Generator:
    if not isinstance(rng, np.random.Generator):
        raise ValueError(f"rng: expected a numpy.random.Generator, got {type(rng).__name__}")
    return rng


def _scalar_time(name: str, value) -> float:
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected a number of GPS seconds, got {value!r}") from None
    if arr.ndim != 0:
        raise ValueError(f"{name}: expected a scalar epoch, got shape {arr.shape}")
    t = float(arr)
    if not np.isfinite(t):
        raise ValueError(f"{name}: must be finite, got {t!r}")
    return t


def _broadcasts_to(name: str, arr: np.ndarray, shape: tuple, what: str) -> None:
    try:
        ok = np.broadcast_shapes(arr.shape, shape) == tuple(shape)
    except ValueError:
        ok = False
    if not ok:
        raise ValueError(f"{name}: shape {arr.shape} does not broadcast to {what} {tuple(shape)}")


# ---------------------------------------------------------------------------
# one epoch
# ---------------------------------------------------------------------------

def look_angles(rx_pos_ecef_m, geometry: Geometry, ell=None) -> tuple[np.ndarray, np.ndarray]:
    """Azimuth and elevation (..., S), rad, of each satellite seen from the receiver.

    The target is the satellite at emission in the ECEF frame of the reception time
    (``geometry.sat_pos_ecef_m``), i.e. the direction the signal arrives from; the
    horizon is the geodetic one of ``ell`` (default WGS-84) at the receiver.
    """
    if not isinstance(geometry, Geometry):
        raise ValueError(f"geometry: expected a ranging.Geometry, got {type(geometry).__name__}")
    rx = finite_vec3("rx_pos_ecef_m", rx_pos_ecef_m)
    az, el, _ = ecef_to_aer(rx[..., None, :], geometry.sat_pos_ecef_m, ell)
    return az, el


def elevation_grid(constellation: Constellation, t_gps_s, rx_pos_ecef_m) -> np.ndarray:
    """Geodetic elevation (T, S), rad, of every satellite at T epochs seen from rx_pos_ecef_m
    (T, 3): instantaneous geometry, no light time -- for visibility checks on a coarse grid."""
    from sitl.gnss import orbits

    t = np.atleast_1d(np.asarray(t_gps_s, dtype=float))
    rx = np.asarray(rx_pos_ecef_m, dtype=float).reshape(t.size, 3)
    el = np.empty((t.size, len(constellation)))
    for i, ti in enumerate(t):
        sp, _ = orbits.sat_state_ecef(constellation, float(ti))
        el[i] = ecef_to_aer(rx[i], sp)[1]
    return el


class EpochGeometry(NamedTuple):
    """Truth geometry of one epoch (see :func:`geometry_track`)."""

    t_gps_s: float
    geometry: Geometry  # (S,) / (S, 3) arrays
    el_rad: np.ndarray  # (S,) above the geodetic horizon (the receiver's mask uses it)
    el_atmo_rad: np.ndarray  # (S,) geocentric elevation (seed 000 eq. 10: atmosphere mapping)


def geometry_track(t_gps_s, rx_pos_ecef_m, rx_vel_ecef_m_s, constellation: Constellation, *,
                   block: int = 256, ell=None):
    """Yield an :class:`EpochGeometry` per epoch of a trajectory, computed in blocks.

    t_gps_s (T,), rx_pos_ecef_m / rx_vel_ecef_m_s (T, 3).  Each block of ``block`` epochs
    goes through ``light_time_geometry`` (and the two elevations) as one batched call; the
    numbers are those of per-epoch calls up to the ephemeris interpolation (both within the
    ranging module's stated tolerance). A generator: only one block is held at a time.
    """
    c = _check_constellation(constellation)
    t = np.asarray(t_gps_s, dtype=float)
    if t.ndim != 1 or not np.all(np.isfinite(t)):
        raise ValueError(f"t_gps_s: expected a 1-D array of finite times, got shape {t.shape}")
    pos = finite_vec3("rx_pos_ecef_m", rx_pos_ecef_m)
    vel = finite_vec3("rx_vel_ecef_m_s", rx_vel_ecef_m_s)
    if pos.shape != (t.size, 3) or vel.shape != (t.size, 3):
        raise ValueError(f"rx_pos_ecef_m and rx_vel_ecef_m_s must have shape ({t.size}, 3), got {pos.shape} "
                         f"and {vel.shape}")
    if isinstance(block, bool) or not isinstance(block, (int, np.integer)) or block < 1:
        raise ValueError(f"block must be an integer >= 1, got {block!r}")
    for k0 in range(0, t.size, block):
        sl = slice(k0, min(k0 + block, t.size))
        geo = light_time_geometry(t[sl], pos[sl], vel[sl], c, ell)
        _, el = look_angles(pos[sl], geo, ell)
        el_atmo = geocentric_elevation_rad(pos[sl][:, None, :], geo.sat_pos_ecef_m)
        arrays = [getattr(geo, f.name) for f in fields(Geometry)]
        for i in range(sl.stop - sl.start):
            g = Geometry(*(a[i] for a in arrays))
            yield EpochGeometry(float(t[k0 + i]), g, el[i], el_atmo[i])


def _observe(rng, t_gps_s, rx_pos_ecef_m, rx_vel_ecef_m_s, clock_bias_m, clock_drift_m_s,
             constellation, receiver, ell):
    """observe() that also returns the truth Geometry."""
    _check_rng(rng)
    c = _check_constellation(constellation)
    if not isinstance(receiver, Receiver):
        raise ValueError(f"receiver: expected a receiver.Receiver, got {type(receiver).__name__}")
    if receiver.n_sats != len(c):
        raise ValueError(f"receiver: tracks {receiver.n_sats} satellites but the constellation has {len(c)}")
    t = _scalar_time("t_gps_s", t_gps_s)
    pos = finite_vec3("rx_pos_ecef_m", rx_pos_ecef_m)
    vel = finite_vec3("rx_vel_ecef_m_s", rx_vel_ecef_m_s)
    batch = receiver.batch_shape
    _broadcasts_to("rx_pos_ecef_m", pos, batch + (3,), "the receiver's batch")
    _broadcasts_to("rx_vel_ecef_m_s", vel, batch + (3,), "the receiver's batch")
    bias = _FINITE("clock_bias_m", clock_bias_m)
    drift = _FINITE("clock_drift_m_s", clock_drift_m_s)
    _broadcasts_to("clock_bias_m", bias, batch, "the receiver's batch")
    _broadcasts_to("clock_drift_m_s", drift, batch, "the receiver's batch")

    pos = np.broadcast_to(pos, batch + (3,))
    geo = light_time_geometry(t, pos, vel, c, ell)
    _, el = look_angles(pos, geo, ell)
    # mask on the geodetic horizon; atmosphere mapped on the geocentric vertical (seed 000, eq. 10)
    el_atmo = geocentric_elevation_rad(pos[..., None, :], geo.sat_pos_ecef_m)
    obs = receiver.step(rng, t, geo.range_m, geo.range_rate_m_s, el, c.carrier_l1_hz, c.system == "G",
                        bias, drift, el_atmo_rad=el_atmo)
    return obs, geo


def observe(rng: np.random.Generator, t_gps_s, rx_pos_ecef_m, rx_vel_ecef_m_s, clock_bias_m,
            clock_drift_m_s, constellation: Constellation, receiver: Receiver, ell=None) -> Observation:
    """One epoch of L1 measurements of every satellite of ``constellation``.

    Parameters
    ----------
    rng : numpy Generator (all noise, fresh ambiguities, random slips).
    t_gps_s : scalar true reception GPS time; must increase from call to call.
    rx_pos_ecef_m, rx_vel_ecef_m_s : (..., 3) true receiver state at t_gps_s (ECEF,
        rotating frame); (...) must broadcast to ``receiver.batch_shape``.
    clock_bias_m, clock_drift_m_s : (...) true receiver clock bias (m) and drift (m/s).
    constellation : S satellites; ``receiver`` must track S satellites in this order.
    receiver : the stateful measurement generator (lock, ambiguities, slips).
    ell : Ellipsoid or name (default WGS-84): rotation rate of the light-time solution
        and the geodetic horizon of the elevation.

    Returns the receiver's :class:`~sitl.gnss.receiver.Observation`, (..., S) arrays,
    NaN where el < mask.  ``Observation.el_rad`` holds the geodetic elevations.
    """
    return _observe(rng, t_gps_s, rx_pos_ecef_m, rx_vel_ecef_m_s, clock_bias_m, clock_drift_m_s,
                    constellation, receiver, ell)[0]


# ---------------------------------------------------------------------------
# a trajectory
# ---------------------------------------------------------------------------

_OBS_STACKED = ("visible", "pseudorange_m", "pseudorange_rate_m_s", "carrier_phase_m", "carrier_phase_cycles",
                "lock_count", "slip", "ambiguity_cycles", "el_rad", "iono_slant_m", "tropo_slant_m")


@dataclass(frozen=True, eq=False)
class ObservationTrack:
    """Epochs of :func:`simulate_receiver`, stacked on a leading axis T.

    Receiver output (as in :class:`~sitl.gnss.receiver.Observation`, with T in front):
    t_gps_s (T,); visible, pseudorange_m, pseudorange_rate_m_s, carrier_phase_m,
    carrier_phase_cycles, lock_count, slip, ambiguity_cycles, el_rad, iono_slant_m,
    tropo_slant_m: (T, *batch, S); wavelength_m: (S,); sat_id: (S,).
    (slip, ambiguity_cycles, el_rad, iono_slant_m, tropo_slant_m are truth, as in
    Observation.)

    Truth for scoring only: clock_bias_m, clock_drift_m_s (T, *batch); range_m,
    range_rate_m_s (T, *batch, S) of the light-time solution, unmasked.  The satellite
    states of that solution are not kept (T x batch x S x 3 floats); recompute them with
    ``ranging.light_time_geometry`` from the true receiver states (deterministic).
    """

    t_gps_s: np.ndarray
    sat_id: np.ndarray
    wavelength_m: np.ndarray
    visible: np.ndarray
    pseudorange_m: np.ndarray
    pseudorange_rate_m_s: np.ndarray
    carrier_phase_m: np.ndarray
    carrier_phase_cycles: np.ndarray
    lock_count: np.ndarray
    slip: np.ndarray
    ambiguity_cycles: np.ndarray
    el_rad: np.ndarray
    iono_slant_m: np.ndarray
    tropo_slant_m: np.ndarray
    clock_bias_m: np.ndarray
    clock_drift_m_s: np.ndarray
    range_m: np.ndarray
    range_rate_m_s: np.ndarray

    def __post_init__(self):
        t = np.asarray(self.t_gps_s)
        if t.ndim != 1 or t.size < 1:
            raise ValueError(f"t_gps_s: expected shape (T,) with T >= 1, got {t.shape}")
        S = np.asarray(self.sat_id).shape
        if len(S) != 1 or np.asarray(self.wavelength_m).shape != S:
            raise ValueError(f"wavelength_m: expected shape {S} like sat_id, got {np.shape(self.wavelength_m)}")
        shape = np.shape(self.pseudorange_m)
        if len(shape) < 2 or shape[0] != t.size or shape[-1] != S[0]:
            raise ValueError(f"pseudorange_m: expected shape ({t.size}, ..., {S[0]}), got {shape}")
        for name in _OBS_STACKED + ("range_m", "range_rate_m_s"):
            if np.shape(getattr(self, name)) != shape:
                raise ValueError(f"{name}: expected shape {shape}, got {np.shape(getattr(self, name))}")
        for name in ("clock_bias_m", "clock_drift_m_s"):
            if np.shape(getattr(self, name)) != shape[:-1]:
                raise ValueError(f"{name}: expected shape {shape[:-1]}, got {np.shape(getattr(self, name))}")

    def __len__(self) -> int:
        return int(self.t_gps_s.shape[0])

    @property
    def batch_shape(self) -> tuple:
        return tuple(self.pseudorange_m.shape[1:-1])

    def epoch(self, k: int) -> Observation:
        """Epoch k as the receiver's Observation (views into the stacked arrays)."""
        if int(k) != k or not -len(self) <= k < len(self):
            raise ValueError(f"k: expected an integer epoch index in [-{len(self)}, {len(self)}), got {k!r}")
        k = int(k)
        return Observation(t_gps_s=float(self.t_gps_s[k]), wavelength_m=self.wavelength_m,
                           **{name: getattr(self, name)[k] for name in _OBS_STACKED})


def simulate_receiver(rng: np.random.Generator, t_gps_s, rx_pos_ecef_m, rx_vel_ecef_m_s,
                      constellation: Constellation, receiver_config: ReceiverConfig | None = None,
                      clock: ClockModel | None = None, clock_bias0_m=0.0, clock_drift0_m_s=0.0,
                      ell=None) -> ObservationTrack:
    """Observations along a receiver trajectory, with the receiver clock simulated.

    Parameters
    ----------
    rng : numpy Generator.  Per epoch k >= 1 the clock step is drawn first, then the
        receiver's noise (so the stream is reproducible from the seed).
    t_gps_s : (T,) strictly increasing true reception GPS times (any spacing).
    rx_pos_ecef_m : (T, *batch, 3) true receiver ECEF positions at t_gps_s.
    rx_vel_ecef_m_s : true ECEF velocities, broadcastable to rx_pos_ecef_m's shape.
    constellation : S satellites (the fixed satellite axis).
    receiver_config : ReceiverConfig (default: seed 000 values).
    clock : ClockModel (default: seed 000 TCXO).  Bias and drift follow
        x(k) = F(dt_k) x(k-1) + xi, Q(dt_k) -- the exact discretisation, so the epochs
        may be unevenly spaced.
    clock_bias0_m, clock_drift0_m_s : clock state at t_gps_s[0], broadcastable to batch.
    ell : see :func:`observe`.

    Returns an :class:`ObservationTrack`.
    """
    _check_rng(rng)
    c = _check_constellation(constellation)
    cfg = ReceiverConfig() if receiver_config is None else receiver_config
    if not isinstance(cfg, ReceiverConfig):
        raise ValueError(f"receiver_config: expected a ReceiverConfig, got {type(cfg).__name__}")
    clk = ClockModel() if clock is None else clock
    if not isinstance(clk, ClockModel):
        raise ValueError(f"clock: expected a ClockModel, got {type(clk).__name__}")
    t = _FINITE("t_gps_s", t_gps_s)
    if t.ndim != 1 or t.size < 1:
        raise ValueError(f"t_gps_s: expected shape (T,) with T >= 1, got {t.shape}")
    if np.any(np.diff(t) <= 0.0):
        raise ValueError("t_gps_s: epochs must be strictly increasing")
    pos = finite_vec3("rx_pos_ecef_m", rx_pos_ecef_m)
    if pos.ndim < 2 or pos.shape[0] != t.size:
        raise ValueError(f"rx_pos_ecef_m: expected shape ({t.size}, ..., 3) (one row per epoch), got {pos.shape}")
    vel = finite_vec3("rx_vel_ecef_m_s", rx_vel_ecef_m_s)
    _broadcasts_to("rx_vel_ecef_m_s", vel, pos.shape, "rx_pos_ecef_m's shape")
    vel = np.broadcast_to(vel, pos.shape)
    batch = pos.shape[1:-1]
    b0 = _FINITE("clock_bias0_m", clock_bias0_m)
    d0 = _FINITE("clock_drift0_m_s", clock_drift0_m_s)
    _broadcasts_to("clock_bias0_m", b0, batch, "the batch")
    _broadcasts_to("clock_drift0_m_s", d0, batch, "the batch")

    T, S = t.size, len(c)
    receiver = Receiver(S, cfg, batch)
    bias = np.empty((T,) + batch)
    drift = np.empty((T,) + batch)
    bias[0], drift[0] = b0, d0
    out = {name: [] for name in _OBS_STACKED}
    rng_m, rate_m_s = np.empty((T,) + batch + (S,)), np.empty((T,) + batch + (S,))
    for k in range(T):
        if k > 0:
            bias[k], drift[k] = clk.step(rng, bias[k - 1], drift[k - 1], t[k] - t[k - 1])
        obs, geo = _observe(rng, t[k], pos[k], vel[k], bias[k], drift[k], c, receiver, ell)
        for name in _OBS_STACKED:
            out[name].append(getattr(obs, name))
        rng_m[k], rate_m_s[k] = geo.range_m, geo.range_rate_m_s
    return ObservationTrack(
        t_gps_s=t.copy(), sat_id=np.array(c.sat_id), wavelength_m=C_M_S / c.carrier_l1_hz,
        **{name: np.stack(v) for name, v in out.items()},
        clock_bias_m=bias, clock_drift_m_s=drift, range_m=rng_m, range_rate_m_s=rate_m_s,
    )


# ---------------------------------------------------------------------------
# the estimator's side
# ---------------------------------------------------------------------------

def ephemeris_for_filter(t_rx_gps_s, pseudorange_m, constellation: Constellation, *,
                         pseudorange_rate_m_s=None, clock_bias_est_m=0.0,
                         ell=None) -> tuple[np.ndarray, np.ndarray]:
    """Satellite states an estimator can compute: ephemeris at the measured transit time.

    tau = (pseudorange - clock_bias_est) / c,
    s   = R3(w_e tau) p(t_rx - tau),  ds/dt_rx = R3 v - tau' (R3 v + w_e z x s)
    (``ranging.sat_state_at_reception_frame``), with tau' = pseudorange_rate / c when
    given, else 0 (the velocity at a fixed transit time, ~1e-2 m/s from the exact one).

    Only receiver outputs and the estimator's own numbers go in: no true range, position
    or clock.  The transit-time error dtau = (pr - clock_bias_est)/c - range/c moves the
    satellite along its inertial velocity, |ds| ~= |R3 v + w_e z x s| |dtau| < 4 km/s *
    |dtau| (about 1.3 mm per 100 m of unmodelled clock bias, tropo, iono or noise).

    Parameters
    ----------
    t_rx_gps_s : (...) reception time as the receiver labels it (GPS s), broadcast
        against pseudorange_m.shape[:-1].
    pseudorange_m : (..., S) pseudoranges, NaN for untracked satellites.
    constellation : the S satellites of the last axis.
    pseudorange_rate_m_s : optional (..., S) pseudorange rates (NaN where untracked).
    clock_bias_est_m : the estimator's current clock-bias estimate, broadcast against
        pseudorange_m.shape[:-1] (default 0: the raw pseudorange).
    ell : Ellipsoid or name whose rotation rate is used (default WGS-84).

    Returns
    -------
    sat_pos_ecef_m, sat_vel_ecef_m_s : (..., S, 3), NaN where the pseudorange is NaN.
    """
    c = _check_constellation(constellation)
    S = len(c)
    try:
        pr = np.asarray(pseudorange_m, dtype=float)
    except (TypeError, ValueError):
        raise ValueError("pseudorange_m: cannot convert to a float array") from None
    if pr.ndim < 1 or pr.shape[-1] != S:
        raise ValueError(f"pseudorange_m: expected shape (..., {S}) (one column per satellite), got {pr.shape}")
    if np.any(np.isinf(pr)):
        raise ValueError("pseudorange_m: values must be finite or NaN (untracked)")
    t = _FINITE("t_rx_gps_s", t_rx_gps_s)
    try:
        np.broadcast_shapes(t.shape, pr.shape[:-1])
    except ValueError:
        raise ValueError(f"t_rx_gps_s: shape {t.shape} does not broadcast with pseudorange_m batch "
                         f"{pr.shape[:-1]}") from None
    b = _FINITE("clock_bias_est_m", clock_bias_est_m)
    try:
        np.broadcast_shapes(b.shape, pr.shape[:-1])
    except ValueError:
        raise ValueError(f"clock_bias_est_m: shape {b.shape} does not broadcast with pseudorange_m batch "
                         f"{pr.shape[:-1]}") from None
    tracked = np.isfinite(pr)
    tau = np.where(tracked, (pr - b[..., None]) / C_M_S, NOMINAL_TAU_S)
    if pseudorange_rate_m_s is None:
        rate = 0.0
    else:
        try:
            prr = np.asarray(pseudorange_rate_m_s, dtype=float)
        except (TypeError, ValueError):
            raise ValueError("pseudorange_rate_m_s: cannot convert to a float array") from None
        if prr.shape != pr.shape:
            raise ValueError(f"pseudorange_rate_m_s: expected shape {pr.shape} like pseudorange_m, got {prr.shape}")
        if np.any(np.isinf(prr)) or np.any(tracked & np.isnan(prr)):
            raise ValueError("pseudorange_rate_m_s: must be finite wherever pseudorange_m is")
        rate = np.where(tracked, prr, 0.0) / C_M_S
    pos, vel = sat_state_at_reception_frame(t, tau, c, rate, ell)
    mask = tracked[..., None]
    return np.where(mask, pos, np.nan), np.where(mask, vel, np.nan)


def visible_count(obs, constellation: Constellation | None = None, system: str | None = None) -> np.ndarray:
    """Number of tracked satellites, (...) or (T, ...), from an Observation, an
    ObservationTrack or a boolean (..., S) array; ``system`` 'G' or 'R' counts one
    system only (needs the constellation)."""
    vis = obs.visible if isinstance(obs, (Observation, ObservationTrack)) else np.asarray(obs)
    if vis.dtype != bool or vis.ndim < 1:
        raise ValueError(f"obs: expected an Observation, ObservationTrack or bool (..., S) array, got {vis.dtype}")
    if system is None:
        return vis.sum(axis=-1)
    if system not in ("G", "R"):
        raise ValueError(f"system: expected 'G', 'R' or None, got {system!r}")
    c = _check_constellation(constellation)
    if vis.shape[-1] != len(c):
        raise ValueError(f"constellation: has {len(c)} satellites, obs has {vis.shape[-1]}")
    return (vis & (c.system == system)).sum(axis=-1)
