"""Guidance laws of time alone (open loop): sinusoidal speed, climb and heading; legs and turns on
a schedule; a static vehicle."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from filters.params import ParamError, param, require, validate

from .kernels import _LAW_HOLD, _LAW_LEGS, _LAW_SINUSOID, _N_PARAMS
from .values import _FINITE, _NONNEG, _POSITIVE, _broadcast, _common_shape, _readonly, _shown


@dataclass(frozen=True, eq=False)
class SinusoidalLaw:
    """Speed, climb and heading as sinusoids of time (seed 002 character).

        v(t)   = speed_mean + speed_amp sin(speed_omega t + speed_phase)      (3-D speed)
        v_u(t) = climb_amp cos(climb_omega t + climb_phase)                   (climb rate)
        psi(t) = heading0 + heading_amp sin(heading_omega t + heading_phase)  (heading)

    so the heading rate is heading_amp heading_omega cos(heading_omega t + heading_phase),
    the altitude h0 + (climb_amp / climb_omega) sin(climb_omega t + climb_phase) (when
    climb_phase = 0) and the speed stays in [speed_mean - speed_amp, speed_mean + speed_amp].
    Every field broadcasts to the batch shape (vehicles).  t is the simulation time, s.
    """

    speed_mean_m_s: Any = param(check=_POSITIVE, doc="mean 3-D speed, m/s (> 0)")
    speed_amp_m_s: Any = param(0.0, check=_NONNEG, doc="amplitude of the speed's sinusoid, m/s (< speed_mean_m_s)")
    speed_omega_rad_s: Any = param(0.0, check=_NONNEG, doc="angular frequency of the speed's sinusoid, rad/s")
    speed_phase_rad: Any = param(0.0, check=_FINITE, doc="phase of the speed's sinusoid at t = 0, rad")
    heading0_rad: Any = param(0.0, check=_FINITE, doc="mean heading, clockwise from north, rad")
    heading_amp_rad: Any = param(0.0, check=_NONNEG, doc="amplitude of the heading's sinusoid, rad")
    heading_omega_rad_s: Any = param(0.0, check=_NONNEG, doc="angular frequency of the heading's sinusoid, rad/s")
    heading_phase_rad: Any = param(0.0, check=_FINITE, doc="phase of the heading's sinusoid at t = 0, rad")
    climb_amp_m_s: Any = param(0.0, check=_NONNEG,
                               doc="amplitude of the climb rate's cosine, m/s (< speed_mean_m_s - speed_amp_m_s: the "
                                   "horizontal speed stays > 0)")
    climb_omega_rad_s: Any = param(0.0, check=_NONNEG, doc="angular frequency of the climb rate's cosine, rad/s")
    climb_phase_rad: Any = param(0.0, check=_FINITE, doc="phase of the climb rate's cosine at t = 0, rad")
    batch_shape: tuple = field(init=False)

    _FIELDS = ("speed_mean_m_s", "speed_amp_m_s", "speed_omega_rad_s", "speed_phase_rad", "heading0_rad",
               "heading_amp_rad", "heading_omega_rad_s", "heading_phase_rad", "climb_amp_m_s",
               "climb_omega_rad_s", "climb_phase_rad")

    def __post_init__(self):
        validate(self)
        object.__setattr__(self, "batch_shape", _broadcast(self, self._FIELDS))
        require(not np.any(self.speed_amp_m_s >= self.speed_mean_m_s), "speed_amp_m_s",
                f"expected values < speed_mean_m_s, got {_shown(self.speed_amp_m_s)}")
        require(not np.any(self.climb_amp_m_s >= self.speed_mean_m_s - self.speed_amp_m_s), "climb_amp_m_s",
                "expected values < speed_mean_m_s - speed_amp_m_s (the horizontal speed must stay > 0), "
                f"got {_shown(self.climb_amp_m_s)}")

    def heading_at(self, t_s):
        return self.heading0_rad + self.heading_amp_rad * np.sin(self.heading_omega_rad_s * t_s
                                                                 + self.heading_phase_rad)

    def initial_heading(self, t_s, y):
        return self.heading_at(t_s)

    def target(self, state, t_next_s=None):
        return None

    def commands(self, t_s, y, aux=None):
        """(speed m/s, climb m/s, heading rate rad/s), each of the batch shape."""
        speed = self.speed_mean_m_s + self.speed_amp_m_s * np.sin(self.speed_omega_rad_s * t_s + self.speed_phase_rad)
        climb = self.climb_amp_m_s * np.cos(self.climb_omega_rad_s * t_s + self.climb_phase_rad)
        w = self.heading_omega_rad_s
        rate = self.heading_amp_rad * w * np.cos(w * t_s + self.heading_phase_rad)
        return speed, climb, rate

    def advance(self, state, ell):
        return state.wp_index

    def _kernel_args(self):
        p = np.stack([np.ravel(getattr(self, f)) for f in self._FIELDS], axis=-1)
        return _LAW_SINUSOID, p, {}


def _switch_times(key: str, value) -> np.ndarray:
    """A strictly increasing 1-D array of finite times (read-only)."""
    a = _FINITE(key, value)
    if a.ndim != 1 or (a.size > 1 and np.any(np.diff(a) <= 0)):
        raise ParamError(key, f"expected a strictly increasing 1-D array of times, got {_shown(value)}")
    return a


@dataclass(frozen=True, eq=False)
class LegsAndTurns:
    """Straight legs and constant-rate turns on a time schedule, constant speed, level.

    The heading rate is turn_rates_rad_s[..., j] on the j-th interval of the schedule
    (-inf, switch_times_s[0]), [switch_times_s[0], switch_times_s[1]), ..., [switch_times_s[-1], inf):
    0 on a leg, the turn rate (rad/s, > 0 to the right) in a turn.
    speed_m_s, heading0_rad (heading at the start) broadcast to the batch shape;
    switch_times_s (K,) strictly increasing, turn_rates_rad_s (..., K + 1).
    The integrator cuts its steps at the switch times (``breakpoints_s``) and takes each
    step's interval from its midpoint, so a switch never falls inside an RK4 step.
    """

    speed_m_s: Any = param(check=_NONNEG, doc="speed, m/s (>= 0)")
    heading0_rad: Any = param(check=_FINITE, doc="heading at the start, clockwise from north, rad")
    switch_times_s: Any = param(check=_switch_times, doc="the schedule's switch times (K,), strictly increasing, s")
    turn_rates_rad_s: Any = param(check=_FINITE,
                                  doc="heading rate on each of the K + 1 intervals of the schedule (..., K + 1), "
                                      "rad/s (> 0 to the right; 0 on a leg)")
    batch_shape: tuple = field(init=False)

    def __post_init__(self):
        validate(self)
        sw, tr = self.switch_times_s, self.turn_rates_rad_s
        require(tr.ndim >= 1 and tr.shape[-1] == sw.size + 1, "turn_rates_rad_s",
                f"expected shape (..., {sw.size + 1}) (one rate per interval), got {tr.shape}")
        shape = _common_shape((("speed_m_s", self.speed_m_s.shape), ("heading0_rad", self.heading0_rad.shape),
                               ("turn_rates_rad_s[..., 0]", tr.shape[:-1])))
        object.__setattr__(self, "speed_m_s", _readonly(np.broadcast_to(self.speed_m_s, shape)))
        object.__setattr__(self, "heading0_rad", _readonly(np.broadcast_to(self.heading0_rad, shape)))
        object.__setattr__(self, "turn_rates_rad_s", _readonly(np.broadcast_to(tr, shape + tr.shape[-1:])))
        object.__setattr__(self, "batch_shape", shape)

    breakpoints_s = property(lambda self: self.switch_times_s)

    def initial_heading(self, t_s, y):
        return self.heading0_rad

    def target(self, state, t_next_s=None):
        """The schedule interval of the step [state.t_s, t_next_s] (from its midpoint: the
        integrator cuts its steps at the switch times, so a step lies in one interval)."""
        t = state.t_s if t_next_s is None else 0.5 * (state.t_s + t_next_s)
        return int(np.searchsorted(self.switch_times_s, t, side="right"))

    def commands(self, t_s, y, aux=None):
        j = int(np.searchsorted(self.switch_times_s, t_s, side="right")) if aux is None else aux
        zero = np.zeros(self.batch_shape)
        return self.speed_m_s, zero, self.turn_rates_rad_s[..., j]

    def advance(self, state, ell):
        return state.wp_index

    def _kernel_args(self):
        p = np.zeros((int(np.prod(self.batch_shape, dtype=np.int64)), _N_PARAMS))
        p[:, 0] = np.ravel(self.speed_m_s)
        return _LAW_LEGS, p, {"switch_times_s": self.switch_times_s,
                              "turn_rates_rad_s": self.turn_rates_rad_s.reshape(-1, self.switch_times_s.size + 1)}


def _batch_shape(key: str, value) -> tuple:
    """A batch shape: a tuple of integers >= 0 (one integer n: (n,)), as a tuple of ints."""
    shape = (value,) if isinstance(value, (int, np.integer)) else value
    try:
        dims = tuple(shape)
        ok = not any(isinstance(n, bool) or int(n) != n or n < 0 for n in dims)
    except (TypeError, ValueError, OverflowError):
        ok = False
    if not ok:
        raise ParamError(key, f"expected a tuple of integers >= 0, got {value!r}")
    return tuple(int(n) for n in dims)


@dataclass(frozen=True, eq=False)
class Hold:
    """A static vehicle: speed, climb and heading rate 0 (batch_shape vehicles)."""

    batch_shape: tuple = param((), check=_batch_shape,
                               doc="the batch shape (vehicles): a tuple of integers >= 0, or one integer")

    def __post_init__(self):
        validate(self)

    def initial_heading(self, t_s, y):
        return np.zeros(self.batch_shape)

    def target(self, state, t_next_s=None):
        return None

    def commands(self, t_s, y, aux=None):
        z = np.zeros(self.batch_shape)
        return z, z, z

    def advance(self, state, ell):
        return state.wp_index

    def _kernel_args(self):
        return _LAW_HOLD, np.zeros((int(np.prod(self.batch_shape, dtype=np.int64)), _N_PARAMS)), {}
