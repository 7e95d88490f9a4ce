"""State-space models: small immutable objects that the filters hold.

A transition model (filters.protocols.TransitionModel) answers

    ndim, linear
    f(x, dt) -> (..., n)          x(k+1) = f(x(k)) + w,  w ~ N(0, Q)
    F(x, dt) -> (n, n) | (..., n, n)   Jacobian df/dx ((n, n) for linear models; x may be None)
    Q(dt)    -> (n, n)

and a measurement model (filters.protocols.MeasurementModel) answers

    ndim_meas (m), ndim_state (n)
    h(x)       -> (..., m)        z = h(x) + v,  v ~ N(0, R)
    H(x)       -> (..., m, n)     Jacobian dh/dx
    h_and_H(x) -> (h(x), H(x))    in one pass (what the EKF-type filters call)
    R()        -> (m, m) | (..., m, m)
    R_diag()   -> (m,) | (..., m) when R is diagonal, else None

(``Measurement``: h_and_H from h and H; ``JointMeasurement``: h and H from h_and_H; both
give R from R_diag).

State arrays carry leading batch axes: x (..., n). A measurement model holds its per-step
context (satellite positions, ...) and is cheap to build every step: validation is O(1)
or a cheap shape/sign check, never a copy of the caller's arrays.

Kinematic models order their state derivative-major: for ``ndim_pos = 3`` a constant
velocity state is ``[px, py, pz, vx, vy, vz]`` and a Singer state is
``[px, py, pz, vx, vy, vz, ax, ay, az]``; F = kron(F_axis, I) and Q = kron(Q_axis, I).

Pure numpy/scipy: no I/O, no clocks, no randomness.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from .params import Check, ParamError, array, integer, number, optional, param, require, switch, validate

try:  # optional compiled helpers (numba); numpy is the reference path
    from . import _nbkernels as _nbk
except ImportError:  # pragma: no cover
    _nbk = None

__all__ = [
    "ConstantVelocity",
    "ConstantAcceleration",
    "Singer",
    "ClockGaussMarkov",
    "ClockRandomWalk",
    "Composite",
    "singer_clock_transition",
    "Measurement",
    "JointMeasurement",
    "LinearGaussian",
    "PseudorangeDoppler",
    "ClockFreePseudorangeDoppler",
    "SINGER_CLOCK_N",
    "SINGER_CLOCK_POS",
    "SINGER_CLOCK_BIAS",
    "SINGER_CLOCK_VEL",
    "SINGER_CLOCK_DRIFT",
    "SINGER_CLOCK_ACC",
    "SINGER_CLOCK_ORDER",
    "C_M_S",
]

C_M_S = 299_792_458.0  # speed of light, m/s (kept here so that filters/ imports no sitl)


# --------------------------------------------------------------------------------------
# parameter checks (filters.params; messages name the parameter and its value)

_COUNT = integer(1, numpy=True)
_NONNEGATIVE = number(0, numpy=True)
_POSITIVE = number(0, lo_open=True, numpy=True)
_DT = number(0, numpy=True, what="a finite number >= 0 s")
# a per-step model's arrays: read-only views of the caller's (no copy), shape checked only
_SAT_STATES = array((..., -1, 3), finite=False, nan=True, copy=False, what="a numeric array of shape (..., S, 3)")
_MATRICES = array((..., -1, -1), finite=False, nan=True, copy=False, what="a numeric array of shape (..., m, n)")
_SIGMAS = array(lo=0, lo_open=True, copy=False, what="finite numbers > 0")


def _check_dt(dt: Any) -> float:
    return _DT("dt", dt)


def _per_satellite(key: str, a: np.ndarray, S: int):
    """A checked sigma (_SIGMAS) that must be a scalar or (..., S) (a rule between fields):
    a float for a scalar, else the read-only array."""
    require(a.ndim == 0 or a.shape[-1] in (1, S), key, f"expected a scalar or (..., {S}), got shape {a.shape}")
    return float(a) if a.ndim == 0 else a


def _check_state(x: Any, n: int) -> np.ndarray:
    x = np.asarray(x, dtype=float)
    if x.ndim < 1 or x.shape[-1] != n:
        raise ValueError(f"x must have shape (..., {n}), got shape {x.shape}")
    return x


def _readonly(a: np.ndarray) -> np.ndarray:
    """A read-only view (no copy) so that a frozen model cannot be mutated through it."""
    v = a.view()
    v.flags.writeable = False
    return v


# --------------------------------------------------------------------------------------
# g(x) = N(x) / (d x^p), N an exponential polynomial, without cancellation near x = 0


class _ExpPoly:
    """g(x) = sum_t c_t x^k_t exp(-r_t x) / (d x^p), evaluated stably for x >= 0.

    Near x = 0 the closed form cancels catastrophically (the Singer q11 numerator is
    O(x^5) built from O(1) terms), so for x < x_switch we sum the Taylor series of N
    from x^p upward; its coefficients are exact sums of (-r)^j / j! terms.
    """

    def __init__(self, terms, p: int, d: float = 1.0, n_series: int = 32, x_switch: float = 1.0):
        self.terms = tuple(terms)
        self.p, self.d, self.x_switch = p, d, x_switch
        coef = []
        for j in range(p, p + n_series):
            a = 0.0
            for c, k, r in self.terms:
                if j >= k:
                    a += c * (-r) ** (j - k) / math.factorial(j - k)
            coef.append(a)
        self.series = tuple(reversed(coef))  # for Horner, highest order first

    def __call__(self, x: float) -> float:
        if x < self.x_switch:
            acc = 0.0
            for a in self.series:
                acc = acc * x + a
            return acc / self.d
        n = sum(c * x**k * math.exp(-r * x) for c, k, r in self.terms)
        return n / (self.d * x**self.p)


# Singer (1970) q_ij for unit white-noise intensity, q_ij = T^p g_ij(alpha T); the
# process noise is Q = 2 alpha sigma_a^2 q. Terms (c, k, r) mean c x^k e^{-r x}.
_G11 = _ExpPoly([(1, 0, 0), (-1, 0, 2), (2, 1, 0), (2 / 3, 3, 0), (-2, 2, 0), (-4, 1, 1)], 5, 2)
_G12 = _ExpPoly([(1, 0, 2), (1, 0, 0), (-2, 0, 1), (2, 1, 1), (-2, 1, 0), (1, 2, 0)], 4, 2)
_G13 = _ExpPoly([(1, 0, 0), (-1, 0, 2), (-2, 1, 1)], 3, 2)
_G22 = _ExpPoly([(4, 0, 1), (-3, 0, 0), (-1, 0, 2), (2, 1, 0)], 3, 2)
_G23 = _ExpPoly([(1, 0, 2), (1, 0, 0), (-2, 0, 1)], 2, 2)
_G33 = _ExpPoly([(1, 0, 0), (-1, 0, 2)], 1, 2)
# Singer transition entries: F13 = T^2 (x - 1 + e^-x)/x^2, F23 = T (1 - e^-x)/x.
_F13 = _ExpPoly([(1, 1, 0), (-1, 0, 0), (1, 0, 1)], 2)
_F23 = _ExpPoly([(1, 0, 0), (-1, 0, 1)], 1)


def _ou_integrated(rate: float, T: float):
    """Per-axis [v, a] block of Singer for a first-order Gauss-Markov a with rate `rate`:
    F = [[1, (1-e^-x)/rate], [0, e^-x]], q (unit intensity) = [[q22, q23], [q23, q33]]."""
    x = rate * T
    F = np.array([[1.0, T * _F23(x)], [0.0, math.exp(-x)]])
    q = np.array([[T**3 * _G22(x), T**2 * _G23(x)], [T**2 * _G23(x), T * _G33(x)]])
    return F, q


# --------------------------------------------------------------------------------------
# linear time-invariant kinematics, per axis then kron with I_d


class _LinearKinematic:
    """Shared f/F/Q for models defined per axis as F_axis(dt), Q_axis(dt)."""

    linear = True

    @property
    def ndim(self) -> int:
        return self._order * self.ndim_pos

    def f(self, x, dt):
        """x(k+1) = F x(k), batched over leading axes."""
        x = _check_state(x, self.ndim)
        return x @ self.F(None, dt).T

    def F(self, x, dt):
        """Transition matrix (n, n); x is ignored (linear model)."""
        return np.kron(self._F_axis(_check_dt(dt)), np.eye(self.ndim_pos))

    def Q(self, dt):
        """Exact discrete process noise (n, n)."""
        return np.kron(self._Q_axis(_check_dt(dt)), np.eye(self.ndim_pos))


@dataclass(frozen=True)
class ConstantVelocity(_LinearKinematic):
    """Continuous white-noise acceleration, per axis [p, v]:

    F = [[1, T], [0, 1]],  Q = q [[T^3/3, T^2/2], [T^2/2, T]]  (exact discretisation).
    """

    ndim_pos: int = param(3, check=_COUNT, doc="position axes; the state is [p, v], ndim_pos each")
    q: float = param(check=_NONNEGATIVE, kw_only=True, doc="acceleration PSD, m^2/s^3")

    _order = 2

    def __post_init__(self):
        validate(self)

    def _F_axis(self, T):
        return np.array([[1.0, T], [0.0, 1.0]])

    def _Q_axis(self, T):
        return self.q * np.array([[T**3 / 3, T**2 / 2], [T**2 / 2, T]])


@dataclass(frozen=True)
class ConstantAcceleration(_LinearKinematic):
    """Continuous white-noise jerk, per axis [p, v, a]:

    F = [[1, T, T^2/2], [0, 1, T], [0, 0, 1]],
    Q = q [[T^5/20, T^4/8, T^3/6], [T^4/8, T^3/3, T^2/2], [T^3/6, T^2/2, T]].
    """

    ndim_pos: int = param(3, check=_COUNT, doc="position axes; the state is [p, v, a], ndim_pos each")
    q: float = param(check=_NONNEGATIVE, kw_only=True, doc="jerk PSD, m^2/s^5")

    _order = 3

    def __post_init__(self):
        validate(self)

    def _F_axis(self, T):
        return np.array([[1.0, T, T**2 / 2], [0.0, 1.0, T], [0.0, 0.0, 1.0]])

    def _Q_axis(self, T):
        return self.q * np.array(
            [
                [T**5 / 20, T**4 / 8, T**3 / 6],
                [T**4 / 8, T**3 / 3, T**2 / 2],
                [T**3 / 6, T**2 / 2, T],
            ]
        )


@dataclass(frozen=True)
class Singer(_LinearKinematic):
    """Singer (1970) manoeuvre model, per axis [p, v, a]; seed 001.

    da/dt = -alpha a + w,  E[w w] = 2 alpha sigma_a^2 delta  (stationary std of a: sigma_a)
    F = expm(A T) = [[1, T, (aT - 1 + e^-aT)/a^2], [0, 1, (1 - e^-aT)/a], [0, 0, e^-aT]]
    Q = 2 alpha sigma_a^2 q(alpha, T), q_ij Singer's closed forms (the seed's m_ij), e.g.
    q11 = (1 - e^-2aT + 2aT + 2a^3T^3/3 - 2a^2T^2 - 4aT e^-aT) / (2 a^5),
    q33 = (1 - e^-2aT) / (2a), so Q33 = sigma_a^2 (1 - e^-2aT) as in the seed's
    A(k) = A e^-aT + sigma_a sqrt(1 - e^-2aT) N.
    Evaluated by series for small alpha T (the closed forms cancel there).
    """

    alpha_1_s: float = param(check=_POSITIVE,
                             doc="inverse manoeuvre time constant (acceleration spectrum width), 1/s")
    sigma_a_m_s2: float = param(check=_NONNEGATIVE, doc="stationary std of the acceleration, m/s^2")
    ndim_pos: int = param(3, check=_COUNT, doc="position axes; the state is [p, v, a], ndim_pos each")

    _order = 3

    def __post_init__(self):
        validate(self)

    def _F_axis(self, T):
        x = self.alpha_1_s * T
        return np.array(
            [[1.0, T, T**2 * _F13(x)], [0.0, 1.0, T * _F23(x)], [0.0, 0.0, math.exp(-x)]]
        )

    def _Q_axis(self, T):
        x = self.alpha_1_s * T
        q11, q12, q13 = T**5 * _G11(x), T**4 * _G12(x), T**3 * _G13(x)
        q22, q23, q33 = T**3 * _G22(x), T**2 * _G23(x), T * _G33(x)
        q = np.array([[q11, q12, q13], [q12, q22, q23], [q13, q23, q33]])
        return 2.0 * self.alpha_1_s * self.sigma_a_m_s2**2 * q


# --------------------------------------------------------------------------------------
# receiver clocks, state [bias (m), drift (m/s)]


@dataclass(frozen=True)
class ClockGaussMarkov:
    """Receiver clock of seed 001: bias D' (m), drift V' (m/s), first-order Gauss-Markov drift.

    Default (exact_bias=False), the seed's discrete model as written:
        D'(k) = D' + T V',   V'(k) = V' e^-muT + sigma sqrt(1 - e^-2muT) N(0, 1)
        F = [[1, T], [0, e^-muT]],   Q = diag(0, sigma^2 (1 - e^-2muT)).
    The bias is driven only through the drift, so Q is singular (rank 1).

    exact_bias=True: the exact discretisation of dD'/dt = V', dV'/dt = -mu V' + w with
    E[w w] = 2 mu sigma^2 delta (same stationary drift std sigma):
        F = [[1, (1 - e^-muT)/mu], [0, e^-muT]],  Q = 2 mu sigma^2 [[q22, q23], [q23, q33]]
    with Singer's q (alpha -> mu). The seed's M matrix lists such mv_11, mv_12 entries, but
    its F uses T, and its entries lack the 2 mu factor of its own difference equation.
    """

    mu_1_s: float = param(check=_POSITIVE, doc="oscillator spectrum width (inverse drift correlation time), 1/s")
    sigma_drift_m_s: float = param(check=_NONNEGATIVE, doc="stationary std of the clock drift, m/s")
    exact_bias: bool = param(False, check=switch(numpy=True),
                             doc="the exact discretisation of the bias (False: the seed's D' + T V')")

    linear = True
    ndim = 2

    def __post_init__(self):
        validate(self)

    def f(self, x, dt):
        x = _check_state(x, 2)
        return x @ self.F(None, dt).T

    def F(self, x, dt):
        T = _check_dt(dt)
        if self.exact_bias:
            return _ou_integrated(self.mu_1_s, T)[0]
        return np.array([[1.0, T], [0.0, math.exp(-self.mu_1_s * T)]])

    def Q(self, dt):
        T = _check_dt(dt)
        s2 = self.sigma_drift_m_s**2
        if self.exact_bias:
            return 2.0 * self.mu_1_s * s2 * _ou_integrated(self.mu_1_s, T)[1]
        return np.array([[0.0, 0.0], [0.0, -s2 * math.expm1(-2.0 * self.mu_1_s * T)]])


@dataclass(frozen=True)
class ClockRandomWalk:
    """Receiver clock of seed 000 (eqs 13-15): bias Delta (m), drift (m/s).

    Delta(i+1) = Delta + T dDelta + xi,  dDelta(i+1) = dDelta + xi',
    F = [[1, T], [0, 1]],  Q = c^2 N [[T^3/3, T^2/2], [T^2/2, T]],
    N the two-sided PSD of the forming noise (1/s; seed 000: 0.8e-20).
    """

    psd_1_s: float = param(check=_NONNEGATIVE, doc="two-sided PSD N of the clock's forming noise, 1/s")
    c: float = param(C_M_S, check=_POSITIVE, doc="speed of light (the bias and drift are in m and m/s), m/s")

    linear = True
    ndim = 2

    def __post_init__(self):
        validate(self)

    def f(self, x, dt):
        x = _check_state(x, 2)
        return x @ self.F(None, dt).T

    def F(self, x, dt):
        T = _check_dt(dt)
        return np.array([[1.0, T], [0.0, 1.0]])

    def Q(self, dt):
        T = _check_dt(dt)
        return self.c**2 * self.psd_1_s * np.array([[T**3 / 3, T**2 / 2], [T**2 / 2, T]])


# --------------------------------------------------------------------------------------
# block-diagonal composition with a state permutation


def _transition_models(v) -> tuple:
    """A non-empty tuple of transition models (objects with ndim, linear, f, F and Q)."""
    try:
        blocks = tuple(v)
    except TypeError:
        raise ParamError("", f"expected a tuple of transition models, got {v!r}") from None
    if not blocks:
        raise ParamError("", "expected at least one transition model, got ()")
    for i, b in enumerate(blocks):
        for attr in ("ndim", "linear", "f", "F", "Q"):
            if not hasattr(b, attr):
                raise ParamError("", f"expected transition models, got [{i}] = {b!r} (no {attr})")
    return blocks


def _bools(v) -> np.ndarray:
    """A bool array (anything np.asarray(v, dtype=bool) takes)."""
    try:
        return np.asarray(v, dtype=bool)
    except (TypeError, ValueError):
        raise ParamError("", f"expected a bool array, got {v!r}") from None


def _indices(v) -> tuple:
    """Indices: anything whose items int() takes, as a tuple of ints."""
    try:
        return tuple(int(i) for i in v)
    except (TypeError, ValueError):
        raise ParamError("", f"expected indices, got {v!r}") from None


_INDICES = Check(_indices)


@dataclass(frozen=True, eq=False)
class Composite:
    """Block-diagonal stack of transition models, then a permutation of the state.

    Stacked state s = [s_block0, s_block1, ...]; the model's state is x = s[order], i.e.
    x[i] = s[order[i]].  F = F_s[order][:, order],  Q = Q_s[order][:, order].
    order=None keeps the stacked order.
    """

    blocks: tuple = param(check=Check(_transition_models), doc="the transition models stacked block-diagonally")
    order: tuple | None = param(None, check=optional(_INDICES),
                                doc="the permutation of the stacked state: x[i] = s[order[i]] (None: stacked order)")

    _slices: tuple = field(init=False, repr=False)
    _inverse: np.ndarray = field(init=False, repr=False)
    _perm: np.ndarray = field(init=False, repr=False)
    # F(None, dt) and Q(dt) of a linear composite, memoised per dt: filters call them at
    # every step with the same dt, and assembling them costs more than a batched step.
    _memo: dict = field(init=False, repr=False, default_factory=dict)

    def __post_init__(self):
        validate(self)
        blocks = self.blocks
        n = sum(int(b.ndim) for b in blocks)
        order = tuple(range(n)) if self.order is None else self.order
        require(sorted(order) == list(range(n)), "order", f"expected a permutation of range({n}), got {self.order!r}")
        slices, start = [], 0
        for b in blocks:
            slices.append(slice(start, start + int(b.ndim)))
            start += int(b.ndim)
        perm = np.array(order, dtype=np.intp)
        inverse = np.empty(n, dtype=np.intp)
        inverse[perm] = np.arange(n)
        object.__setattr__(self, "blocks", blocks)
        object.__setattr__(self, "order", order)
        object.__setattr__(self, "_slices", tuple(slices))
        object.__setattr__(self, "_perm", _readonly(perm))
        object.__setattr__(self, "_inverse", _readonly(inverse))

    @property
    def ndim(self) -> int:
        return len(self.order)

    @property
    def linear(self) -> bool:
        return all(bool(b.linear) for b in self.blocks)

    def f(self, x, dt):
        x = _check_state(x, self.ndim)
        if self.linear:
            return x @ self.F(None, dt).T
        s = x[..., self._inverse]
        out = np.concatenate([b.f(s[..., sl], dt) for b, sl in zip(self.blocks, self._slices)], -1)
        return out[..., self._perm]

    def _stack(self, mats):
        batch = np.broadcast_shapes(*(m.shape[:-2] for m in mats))
        out = np.zeros(batch + (self.ndim, self.ndim))
        for m, sl in zip(mats, self._slices):
            out[..., sl, sl] = m
        return out[..., self._perm[:, None], self._perm[None, :]]

    def _memoised(self, key, make):
        out = self._memo.get(key)
        if out is None:
            if len(self._memo) > 64:
                self._memo.clear()
            out = self._memo[key] = _readonly(make())
        return out

    def F(self, x, dt):
        if self.linear:
            return self._memoised(("F", float(dt)), lambda: self._stack([np.asarray(b.F(None, dt), dtype=float)
                                                                         for b in self.blocks]))
        if x is None:
            raise ValueError("x must be given for the Jacobian of a nonlinear Composite")
        s = _check_state(x, self.ndim)[..., self._inverse]
        mats = [
            np.asarray(b.F(None if b.linear else s[..., sl], dt), dtype=float)
            for b, sl in zip(self.blocks, self._slices)
        ]
        return self._stack(mats)

    def Q(self, dt):
        return self._memoised(("Q", float(dt)), lambda: self._stack([np.asarray(b.Q(dt), dtype=float)
                                                                     for b in self.blocks]))


# Seed 001 state order: lambda = [X, Y, Z, D', Vx, Vy, Vz, V', Ax, Ay, Az].
SINGER_CLOCK_N = 11
SINGER_CLOCK_POS = slice(0, 3)
SINGER_CLOCK_BIAS = 3
SINGER_CLOCK_VEL = slice(4, 7)
SINGER_CLOCK_DRIFT = 7
SINGER_CLOCK_ACC = slice(8, 11)
# x = s[SINGER_CLOCK_ORDER] with s = [Singer p(3) v(3) a(3), clock D' V'].
SINGER_CLOCK_ORDER = (0, 1, 2, 9, 3, 4, 5, 10, 6, 7, 8)


def singer_clock_transition(
    alpha_1_s: float = 0.2,
    sigma_a_m_s2: float = 5.0,
    mu_1_s: float = 0.1,
    sigma_clock_drift_m_s: float = 3.0,
    exact_clock_bias: bool = False,
) -> Composite:
    """The 11-state seed 001 model: Singer on 3 axes + Gauss-Markov clock, seed order.

    The seed gives no sigma_a; the default 5 m/s^2 is the aircraft's acceleration from the
    seed's table (an assumption; pass your own).
    """
    return Composite(
        (
            Singer(alpha_1_s, sigma_a_m_s2, 3),
            ClockGaussMarkov(mu_1_s, sigma_clock_drift_m_s, exact_clock_bias),
        ),
        SINGER_CLOCK_ORDER,
    )


# --------------------------------------------------------------------------------------
# measurement models


def _R_from_diag(model):
    d = model.R_diag()
    if d is None:
        raise TypeError(f"{type(model).__name__}.R_diag() returned None: a model with a full R defines R()")
    d = np.asarray(d, dtype=float)
    return d[..., None] * np.eye(d.shape[-1])


class Measurement:
    """Base of a measurement model written with h(x) and H(x): h_and_H(x) from them, R() from a
    diagonal R_diag()."""

    def h_and_H(self, x):
        return self.h(x), self.H(x)

    def R(self):
        return _R_from_diag(self)


class JointMeasurement:
    """Base of a measurement model that computes h and H in one pass (``h_and_H``): h and H
    come from it, R() from a diagonal R_diag()."""

    def h(self, x):
        return self.h_and_H(x)[0]

    def H(self, x):
        return self.h_and_H(x)[1]

    def R(self):
        return _R_from_diag(self)


@dataclass(frozen=True, eq=False)
class LinearGaussian(Measurement):
    """z = H x + v,  v ~ N(0, R).  H (m, n) or (..., m, n); R (m, m) or (..., m, m)."""

    H_matrix: np.ndarray = param(check=_MATRICES, doc="measurement matrix H, (m, n) or (..., m, n)")
    R_matrix: np.ndarray = param(check=_MATRICES, doc="measurement noise covariance R, (m, m) or (..., m, m)")

    def __post_init__(self):
        validate(self)
        m = self.H_matrix.shape[-2]
        require(self.R_matrix.shape[-2:] == (m, m), "R_matrix",
                f"expected shape (..., {m}, {m}), got shape {self.R_matrix.shape}")

    @property
    def ndim_meas(self) -> int:
        return self.H_matrix.shape[-2]

    @property
    def ndim_state(self) -> int:
        return self.H_matrix.shape[-1]

    def h(self, x):
        x = _check_state(x, self.ndim_state)
        return (self.H_matrix @ x[..., None])[..., 0]

    def H(self, x):
        """(..., m, n), a read-only broadcast view of H."""
        x = _check_state(x, self.ndim_state)
        batch = np.broadcast_shapes(x.shape[:-1], self.H_matrix.shape[:-2])
        return np.broadcast_to(self.H_matrix, batch + self.H_matrix.shape[-2:])

    def R(self):
        return self.R_matrix

    def R_diag(self):
        R = self.R_matrix
        d = np.diagonal(R, axis1=-2, axis2=-1)
        off = R - d[..., None] * np.eye(R.shape[-1])
        return d.copy() if not np.any(off) else None


def _index3(name: str, idx, n: int) -> tuple:
    """Three state indices in [0, n) (a tuple or a slice of range(n)): a rule between fields."""
    if isinstance(idx, slice):
        idx = tuple(range(n))[idx]
    idx = _INDICES(name, idx)
    require(len(idx) == 3 and all(0 <= i < n for i in idx), name, f"expected 3 indices in [0, {n}), got {idx!r}")
    return idx


def _as_index(idx: tuple):
    """A slice when contiguous (a view, no copy), else the tuple for fancy indexing."""
    if all(b - a == 1 for a, b in zip(idx, idx[1:])):
        return slice(idx[0], idx[-1] + 1)
    return list(idx)


def _compiled_pr_prr(model, x):
    """PseudorangeDoppler.h by the compiled kernel, or None when it does not apply.

    Applies when x is (..., M..., n) with the satellites' batch shape M... as its
    trailing batch axes (e.g. sigma points (K, N, n) against satellites (N, S, 3)) and
    scalar sigmas are irrelevant here (h has no noise).
    """
    if _nbk is None:
        return None
    sp, sv = model.sat_pos_ecef_m, model.sat_vel_ecef_m_s
    mb = sp.shape[:-2]
    xb = x.shape[:-1]
    if sv.shape != sp.shape or len(xb) < len(mb) or xb[len(xb) - len(mb):] != mb:
        return None
    M = int(np.prod(mb, dtype=np.int64))
    L = int(np.prod(xb, dtype=np.int64)) // max(M, 1)
    S = sp.shape[-2]
    kernel = _nbk.pr_prr_h_par if L * M >= 256 else _nbk.pr_prr_h_ser
    out = kernel(np.ascontiguousarray(x, dtype=float).reshape(L, M, model.n),
                        np.ascontiguousarray(sp, dtype=float).reshape(M, S, 3),
                        np.ascontiguousarray(sv, dtype=float).reshape(M, S, 3),
                        np.asarray(model.idx_pos, np.int64), np.asarray(model.idx_vel, np.int64),
                        model.idx_bias, model.idx_drift)
    return out.reshape(xb + (2 * S,))


class _PseudorangeRows:
    """The row layout shared by the pseudorange / pseudorange-rate models: S satellites
    (sat_pos_ecef_m (..., S, 3)), all pseudoranges then all rates."""

    @property
    def n_sats(self) -> int:
        return self.sat_pos_ecef_m.shape[-2]

    @property
    def ndim_meas(self) -> int:
        return 2 * self.n_sats


@dataclass(frozen=True, eq=False)
class PseudorangeDoppler(_PseudorangeRows):
    """Pseudoranges and pseudorange rates to S satellites; seed 001 (and seed 000 eq. 20-22).

    Stacked measurement (all pseudoranges, then all rates), m = 2S:
        z = [pr_1 .. pr_S, prr_1 .. prr_S]
        pr_i  = |S_i - X| + D'
        prr_i = u_i . (V_S_i - V) + V',   u_i = (S_i - X) / |S_i - X|
    (range rate positive when the range grows). Jacobian rows:
        d pr_i / dX  = -u_i',                          d pr_i / dD'  = 1
        d prr_i / dX = -(V_S_i - V)' (I - u_i u_i') / |S_i - X|,
        d prr_i / dV = -u_i',                          d prr_i / dV' = 1
    Satellite states are given in the reception-time ECEF frame (light time and Earth
    rotation already applied by the caller), so h has no light-time iteration.

    sat_pos_ecef_m, sat_vel_ecef_m_s: (..., S, 3); sigma_pr_m, sigma_prr_m_s: scalar, (S,)
    or (..., S). R = diag(sigma_pr^2, sigma_prr^2).
    """

    sat_pos_ecef_m: np.ndarray = param(check=_SAT_STATES,
                                       doc="satellite positions (reception-time ECEF), (..., S, 3), m")
    sat_vel_ecef_m_s: np.ndarray = param(check=_SAT_STATES,
                                         doc="satellite velocities (reception-time ECEF), (..., S, 3), m/s")
    sigma_pr_m: Any = param(check=_SIGMAS, doc="pseudorange noise (1 sigma): a scalar, (S,) or (..., S), m")
    sigma_prr_m_s: Any = param(check=_SIGMAS,
                               doc="pseudorange-rate noise (1 sigma): a scalar, (S,) or (..., S), m/s")
    idx_pos: Sequence[int] = (0, 1, 2)  # the position's 3 state indices (or a slice), checked against n
    idx_vel: Sequence[int] = (4, 5, 6)  # the velocity's 3 state indices (or a slice), checked against n
    idx_bias: int = param(3, check=integer(0, numpy=True), doc="state index of the clock bias (m)")
    idx_drift: int = param(7, check=integer(0, numpy=True), doc="state index of the clock drift (m/s)")
    n: int = param(11, check=_COUNT, doc="state dimension")

    def __post_init__(self):
        validate(self)
        n = self.n
        sp, sv = self.sat_pos_ecef_m, self.sat_vel_ecef_m_s
        S = sp.shape[-2]
        require(S >= 1, "sat_pos_ecef_m", f"expected (..., S, 3) with S >= 1, got shape {sp.shape}")
        require(sv.shape[-2:] == sp.shape[-2:], "sat_vel_ecef_m_s", f"expected shape (..., {S}, 3), got shape {sv.shape}")
        for name in ("sigma_pr_m", "sigma_prr_m_s"):
            object.__setattr__(self, name, _per_satellite(name, getattr(self, name), S))
        ip = _index3("idx_pos", self.idx_pos, n)
        iv = _index3("idx_vel", self.idx_vel, n)
        for name in ("idx_bias", "idx_drift"):
            require(getattr(self, name) < n, name, f"expected an index in [0, {n}), got {getattr(self, name)}")
        require(len(set(ip + iv + (self.idx_bias, self.idx_drift))) == 8, "idx_drift",
                f"idx_pos, idx_vel, idx_bias, idx_drift must be distinct, got {ip}, {iv}, {self.idx_bias}, "
                f"{self.idx_drift}")
        object.__setattr__(self, "idx_pos", ip)
        object.__setattr__(self, "idx_vel", iv)

    @property
    def ndim_state(self) -> int:
        return self.n

    def _geometry(self, x):
        """Line of sight u (..., S, 3), range rho (..., S), relative velocity w (..., S, 3).

        Written with explicit components (no einsum over a length-3 axis): this runs at
        every step on 10,000-trial batches and dominates the step outside the kernels.
        """
        x = _check_state(x, self.n)
        X = x[..., _as_index(self.idx_pos)]
        V = x[..., _as_index(self.idx_vel)]
        d = self.sat_pos_ecef_m - X[..., None, :]
        rho = np.sqrt(d[..., 0] ** 2 + d[..., 1] ** 2 + d[..., 2] ** 2)
        u = d / rho[..., None]
        w = self.sat_vel_ecef_m_s - V[..., None, :]
        uw = u[..., 0] * w[..., 0] + u[..., 1] * w[..., 1] + u[..., 2] * w[..., 2]
        return x, u, rho, w, uw

    def h(self, x):
        # The UKF calls this on (2n+1) x trials sigma points: a compiled loop when the
        # batch shapes allow it, else numpy component by component.
        x = _check_state(x, self.n)
        fast = _compiled_pr_prr(self, x)
        if fast is not None:
            return fast
        ip, iv = tuple(self.idx_pos), tuple(self.idx_vel)
        sp, sv = self.sat_pos_ecef_m, self.sat_vel_ecef_m_s
        dx = sp[..., 0] - x[..., ip[0], None]
        dy = sp[..., 1] - x[..., ip[1], None]
        dz = sp[..., 2] - x[..., ip[2], None]
        rho = np.sqrt(dx * dx + dy * dy + dz * dz)
        uw = (dx * (sv[..., 0] - x[..., iv[0], None]) + dy * (sv[..., 1] - x[..., iv[1], None])
              + dz * (sv[..., 2] - x[..., iv[2], None])) / rho
        return self._h(x, rho, uw)

    def _h(self, x, rho, uw):
        out = np.empty(rho.shape[:-1] + (2 * self.n_sats,))
        S = self.n_sats
        np.add(rho, x[..., self.idx_bias, None], out=out[..., :S])
        np.add(uw, x[..., self.idx_drift, None], out=out[..., S:])
        return out

    def H(self, x):
        x, u, rho, w, uw = self._geometry(x)
        return self._H(u, rho, w, uw)

    def _H(self, u, rho, w, uw):
        S = self.n_sats
        ip, iv = _as_index(self.idx_pos), _as_index(self.idx_vel)
        H = np.zeros(u.shape[:-2] + (2 * S, self.n))
        H[..., :S, ip] = -u
        H[..., :S, self.idx_bias] = 1.0
        H[..., S:, ip] = (uw[..., None] * u - w) / rho[..., None]
        H[..., S:, iv] = -u
        H[..., S:, self.idx_drift] = 1.0
        return H

    def h_and_H(self, x):
        """(h(x), H(x)) sharing one geometry evaluation."""
        x = _check_state(x, self.n)
        sp = self.sat_pos_ecef_m
        if (_nbk is not None and x.ndim == 2 and sp.ndim == 3 and sp.shape[0] == x.shape[0]
                and self.sat_vel_ecef_m_s.shape == sp.shape):
            kernel = _nbk.pr_prr_h_H_par if x.shape[0] >= 256 else _nbk.pr_prr_h_H_ser
            return kernel(np.ascontiguousarray(x), np.ascontiguousarray(sp),
                                   np.ascontiguousarray(self.sat_vel_ecef_m_s),
                                   np.asarray(self.idx_pos, np.int64), np.asarray(self.idx_vel, np.int64),
                                   self.idx_bias, self.idx_drift)
        x, u, rho, w, uw = self._geometry(x)
        return self._h(x, rho, uw), self._H(u, rho, w, uw)

    def R_diag(self):
        cached = self.__dict__.get("_r_diag")
        if cached is not None:  # the filters ask for it more than once per step
            return cached
        S = self.n_sats
        pr, prr = np.square(self.sigma_pr_m), np.square(self.sigma_prr_m_s)
        batch = np.broadcast_shapes(np.shape(pr)[:-1], np.shape(prr)[:-1])
        out = _readonly(np.concatenate(
            [np.broadcast_to(pr, batch + (S,)), np.broadcast_to(prr, batch + (S,))], axis=-1
        ))
        object.__setattr__(self, "_r_diag", out)
        return out

    def R(self):
        d = self.R_diag()
        return d[..., None] * np.eye(d.shape[-1])


@dataclass(frozen=True, eq=False)
class ClockFreePseudorangeDoppler(_PseudorangeRows, JointMeasurement):
    """Clock-free pseudoranges and range rates to S satellites, state x = [X (3), V (3)].

        z = [pr_1 .. pr_S, prr_1 .. prr_S],   pr_j = |S_j - X|,
        prr_j = u_j . (V_S_j - V),  u_j = (S_j - X) / |S_j - X|  (positive when receding)
        d pr_j / dX = -u_j',   d prr_j / dX = (prr_j u_j - (V_S_j - V))' / |S_j - X|,
        d prr_j / dV = -u_j'.

    PseudorangeDoppler without the clock states (seed 002: a receiver without a clock; with
    one, three satellites would not fix the position).
    Untracked channels (tracked False) give h = 0, a zero H row and variance 1: with the
    caller's z = 0 there, the innovation and the gain column are exactly 0.

    sat_pos_ecef_m, sat_vel_ecef_m_s (..., S, 3) (NaN allowed where untracked);
    var_pr_m2, var_prr_m2_s2 scalars or (..., S); tracked (..., S) bool or None (all).
    """

    sat_pos_ecef_m: np.ndarray = param(check=_SAT_STATES, doc="satellite positions (reception-time ECEF), "
                                                             "(..., S, 3), NaN allowed where untracked, m")
    sat_vel_ecef_m_s: np.ndarray = param(check=_SAT_STATES, doc="satellite velocities (reception-time ECEF), "
                                                               "(..., S, 3), NaN allowed where untracked, m/s")
    var_pr_m2: Any = param(check=_SIGMAS, doc="pseudorange noise variance: a scalar or (..., S), m^2")
    var_prr_m2_s2: Any = param(check=_SIGMAS, doc="pseudorange-rate noise variance: a scalar or (..., S), m^2/s^2")
    tracked: Any = param(None, check=optional(Check(_bools)),
                         doc="the tracked satellites, (..., S) bool (None: all)")

    def __post_init__(self):
        validate(self)
        sp, sv = self.sat_pos_ecef_m, self.sat_vel_ecef_m_s
        require(sv.shape[-2:] == sp.shape[-2:], "sat_vel_ecef_m_s",
                f"expected shape (..., {sp.shape[-2]}, 3), got {sv.shape}")
        tr = np.ones(sp.shape[:-1], bool) if self.tracked is None else self.tracked
        tr = np.broadcast_to(tr, np.broadcast_shapes(tr.shape, sp.shape[:-1], sv.shape[:-1]))
        m3 = tr[..., None]
        # Untracked satellites sit at the Earth's centre: finite geometry, masked afterwards.
        object.__setattr__(self, "sat_pos_ecef_m", np.where(m3, sp, 0.0))
        object.__setattr__(self, "sat_vel_ecef_m_s", np.where(m3, sv, 0.0))
        object.__setattr__(self, "tracked", tr)

    @property
    def ndim_state(self) -> int:
        return 6

    def h_and_H(self, x):
        x = np.asarray(x, dtype=float)
        if x.ndim < 1 or x.shape[-1] != 6:
            raise ValueError(f"x must have shape (..., 6), got {x.shape}")
        d = self.sat_pos_ecef_m - x[..., None, 0:3]
        rho = np.sqrt(np.sum(d * d, axis=-1))
        u = d / rho[..., None]
        w = self.sat_vel_ecef_m_s - x[..., None, 3:6]
        uw = np.sum(u * w, axis=-1)
        tr = self.tracked
        S = self.n_sats
        hx = np.concatenate([np.where(tr, rho, 0.0), np.where(tr, uw, 0.0)], axis=-1)
        H = np.zeros(hx.shape[:-1] + (2 * S, 6))
        t3 = tr[..., None]
        H[..., :S, 0:3] = np.where(t3, -u, 0.0)
        H[..., S:, 0:3] = np.where(t3, (uw[..., None] * u - w) / rho[..., None], 0.0)
        H[..., S:, 3:6] = np.where(t3, -u, 0.0)
        return hx, H

    def R_diag(self):
        S = self.n_sats
        tr = self.tracked
        pr = np.where(tr, np.broadcast_to(self.var_pr_m2, tr.shape), 1.0)
        prr = np.where(tr, np.broadcast_to(self.var_prr_m2_s2, tr.shape), 1.0)
        return np.concatenate([pr, prr], axis=-1).reshape(tr.shape[:-1] + (2 * S,))
