"""Integrity layer (seed 003): fault detection, isolation and robust, adaptive updates,
wrapped around any filter's update (EKF, UKF, U-D).

Per measurement row j, against the prior (x-, P-) of the epoch:

    nu_j = z_j - h_j(x-),   a_j = sqrt((H P- H' + R)_jj),   beta_j = nu_j / a_j

Healthy: beta_j ~ N(0, 1). Tests (the seed's):
* jumps and outliers: the 3-sigma rule |beta_j| >= ``jump_sigma`` (P = 0.9973 inside);
* gradual faults (drifts, ramps), over a sliding window of ``window`` epochs (k = the epochs
  in the window so far):
  - the seed's test: the mean of beta_j^2 against the chi-square tolerance chi2_{1-a}(k)/k
    (a = ``window_alpha``); it sees a growing spread as well as a bias;
  - a bias test: (sum of beta_j)^2 / k ~ chi2(1) against chi2_{1-a}(1) (a = ``bias_alpha``).
    The innovations of a consistent filter are white, so this is exact; for a slow ramp it
    is far more powerful than the mean square (a bias b in beta moves the sum by k b, the
    sum of squares only by k b^2).
  Samples enter the windows winsorised at the jump threshold J (beta clipped to [-J, J],
  beta^2 to J^2), so one outlier does not read as a drift while a ramp that has already grown
  past J still counts fully toward it; missing epochs enter as healthy values (1 and 0).
Isolation is per *channel*, a group of rows (a satellite's pseudorange and rate, a UAV link's
range and Doppler, one radar axis), given by ``channels`` (m,) ints:
* a row failing the jump test is not used this epoch (its channel's other rows still are);
* a channel with a drift alarm, or with jumps on ``persist`` consecutive epochs (a step that
  stays), is excluded until it shows no jump for ``readmit_after`` consecutive epochs; its
  innovations are still computed (against the prior) while it is out. The window tests do
  not judge an excluded channel: while it is out the filter does not track its slow errors
  (bias states, correlated noise), so its innovations are not white and the window sums
  would keep alarming on a healthy channel (a cascade seen on fault-free runs). A
  readmitted channel starts a fresh window of healthy values, so a fault that is still
  there trips the window tests again within their detection delay.
Excluded rows are made inert (H row = 0, nu = 0: no information and no NIS) -- per batch
member, so each trial or vehicle isolates its own channels.
Redundancy (``min_channels`` k, 0: no limit): a member leaves rows or channels out only while at
least k of its present channels (a row not missing) stay in -- where the estimate needs k
channels to stay observable (a clock-free fix needs three satellites), isolating below that
would lose the fix, and a drifting estimate soon makes the faulty channel look clean again. Per
member and epoch the most isolation that keeps k channels in is applied: the excluded channels
and the jumped rows (k channels keep all their rows); else only the excluded channels (jumped
rows used); else none (detect only: every fault reported as with ``isolate=False``, a channel
that was out comes back and is reported readmitted). With exactly k channels present the
monitored update is the plain one.
Robust update (Huber-type M-estimation): admitted rows with |beta_j| > ``huber_c`` get the
weight w = huber_c / |beta_j| applied as R_jj / w (quadratic inside the threshold, linear
outside), one reweighting at the prior.
Adaptive R (innovation-based, Mehra): r_j <- (1 - lam_j) r_j + lam_j (nu_j^2 - (H P- H')_jj) on
admitted rows, starting from the nominal R_jj, and the update uses max(R_jj, r_j) (the nominal R
is a floor: the estimate can only say the sensor is worse than specified). Each sample is
weighted by its precision: var(nu_j^2 - (H P- H')_jj) = 2 ((H P- H')_jj + R_jj)^2, so
lam_j = lam (R_jj / ((H P- H')_jj + R_jj))^2 -- lam itself at a well-known prior, next to nothing
while the prior is wide (a converging filter's first epochs; before, the first sample became the
estimate and inflated R for tens of seconds: the integrity experiment's fault-free position RMSE
+0.069 +- 0.023 m on 3.03 m, now +0.0025 +- 0.0058 m; 200 trials, seed 3). Adaptive Q is filters.adaptive (eq 7),
a layer on the prediction.

Everything is a pure function of a MonitorState (arrays with the batch axes, some kept
lane-tiled for the kernel); `step` returns the update result, the new state and a Report of the epoch's
statistics, alarms, exclusions and readmissions (the caller turns those into bus events).
The monitor linearises the model at x- for beta (H from the model); the wrapped update
(``update``) then runs unchanged on the masked, reweighted model -- for a UKF the betas use
the linearised innovation variance, the update its own unscented one.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import scipy.special  # chi2.isf(a, k) is chdtri(k, a), without scipy.stats' ~1 s import

from .ekf import UpdateResult, ekf_update, measure
from .params import integer, number, optional, param, switch, validate
from .protocols import MeasurementModel

__all__ = ["GuardedModel", "IntegrityConfig", "IntegrityMonitor", "MonitorState", "Report"]


_PROBABILITY = number(0, lo_open=True, hi=1, hi_open=True, numpy=True)


@dataclass(frozen=True)
class IntegrityConfig:
    jump_sigma: float = param(3.0, check=number(0, lo_open=True, finite=False, numpy=True),
                              doc="|beta| at or above which a row is a jump / outlier (inf: no jump test)")
    window: int = param(10, check=integer(1, numpy=True), doc="epochs of the sliding chi-square drift test")
    window_alpha: float = param(1e-3, check=_PROBABILITY,
                                doc="false-alarm probability of the mean-square test per row-epoch")
    bias_alpha: float | None = param(1e-3, check=optional(_PROBABILITY),
                                     doc="false-alarm probability of the bias test per row-epoch (None: no bias test)")
    persist: int = param(2, check=integer(1, numpy=True),
                         doc="consecutive jump epochs that exclude the channel (a step that stays)")
    readmit_after: int = param(10, check=integer(1, numpy=True),
                               doc="consecutive clean epochs before an excluded channel comes back")
    huber_c: float | None = param(None, check=optional(number(0, lo_open=True, numpy=True)),
                                  doc="Huber threshold on |beta| (None: plain quadratic update)")
    adapt_r: bool = param(False, check=switch(numpy=True),
                          doc="innovation-based R estimate (the nominal R is the floor)")
    r_forget: float = param(0.02, check=number(0, lo_open=True, hi=1, numpy=True),
                            doc="exponential forgetting factor lam of the R estimate, 0 < lam <= 1")
    isolate: bool = param(True, check=switch(numpy=True),
                          doc="isolate faulty rows and channels (False: detect and report only, every row used as "
                              "by the plain filter)")
    min_channels: int = param(0, check=integer(0, numpy=True),
                              doc="isolate only while this many present channels stay in (below: detect only; "
                                  "0: no limit)")

    def __post_init__(self):
        validate(self)

    def drift_thresholds(self) -> np.ndarray:
        """(window,) tolerance on the mean of beta^2 over k = 1..window epochs (read-only, cached)."""
        return _drift_thresholds(float(self.window_alpha), int(self.window))

    def bias_threshold(self) -> float:
        """Tolerance of the bias test, chi2_{1-a}(1) (inf without the test)."""
        return math.inf if self.bias_alpha is None else _chi2_isf_1(float(self.bias_alpha))


@functools.lru_cache(maxsize=64)
def _drift_thresholds(alpha, W):
    k = np.arange(1, W + 1)
    out = scipy.special.chdtri(k, alpha) / k
    out.flags.writeable = False
    return out


@functools.lru_cache(maxsize=64)
def _chi2_isf_1(alpha):
    return float(scipy.special.chdtri(1, alpha))


_TILED = ("sum_sq", "sum_b", "jump_run", "excluded", "clean_run", "r_est")


def _tile(a, B):
    """(..., k) -> (G, k, B), G = ceil(N / B), N the batch size: trial t at [t // B, :, t % B] (a
    lane-tiled copy; idle lanes of the last group 0)."""
    a = np.asarray(a)
    k = a.shape[-1]
    f = a.reshape(-1, k)
    N = f.shape[0]
    G = -(-N // B)
    out = np.zeros((G, B, k), dtype=a.dtype)
    out.reshape(G * B, k)[:N] = f
    return np.ascontiguousarray(out.transpose(0, 2, 1))


def _untile(t, batch):
    """The inverse of _tile: (G, k, B) -> batch + (k,) (a copy)."""
    G, k, B = t.shape
    N = math.prod(batch)
    return np.ascontiguousarray(t.transpose(0, 2, 1).reshape(G * B, k)[:N]).reshape(tuple(batch) + (k,))


class MonitorState:
    """The monitor's state between epochs; functional: ``step`` never modifies a state it is
    given (a caller may keep one and step from it again, as the ground station's lag window
    does). ``take`` and ``merge`` step a subset of the batch rows (a flat batch axis).

    Fields (read as attributes, constructed positionally, ``_replace``), as a NamedTuple's:

    ring_b: ``window`` arrays (..., m): the last beta per row, winsorised to [-J, J], NaN for a
        missing epoch (which counts as the healthy beta = 0, beta^2 = 1); never modified
    sum_sq (..., m): the window's sum of beta^2 (running: + the new sample - the one leaving);
    sum_b (..., m): the window's sum of beta; pos: next ring slot; count: epochs seen, for the
    partial-window tolerance (saturates at window); jump_run (..., C): consecutive epochs with a
    jump on the channel; excluded (..., C) bool; clean_run (..., C): consecutive clean epochs (for
    readmission); r_est (..., m): innovation-based R estimate (NaN until the first sample: the
    nominal R); steps: epochs processed (the running sums are recomputed exactly every RESUM
    epochs); stale (..., m) int32 or None: the slot leaving at epoch ``steps`` counts as a healthy
    value while ``steps < stale`` (a readmitted channel's fresh window; an epoch number, so
    nothing counts it down; None: no such row).

    The compiled monitor keeps sum_sq, sum_b, r_est, jump_run, excluded and clean_run lane-tiled
    (filters/_nbintegrity.py reads and writes them as contiguous blocks: _tile); each form is
    made from the other when first read, so a state the kernel made and nothing else reads is
    never converted."""

    _fields = ("ring_b", "sum_sq", "sum_b", "pos", "count", "jump_run", "excluded", "clean_run", "r_est", "steps",
               "stale")
    __slots__ = ("ring_b", "pos", "count", "steps", "stale", "_std", "_til", "_batch")

    def __init__(self, ring_b, sum_sq, sum_b, pos, count, jump_run, excluded, clean_run, r_est, steps=0,
                 stale=None):
        self.ring_b, self.pos, self.count, self.steps, self.stale = ring_b, pos, count, steps, stale
        self._std = {"sum_sq": sum_sq, "sum_b": sum_b, "jump_run": jump_run, "excluded": excluded,
                     "clean_run": clean_run, "r_est": r_est}
        self._til = None
        self._batch = np.shape(sum_sq)[:-1]

    @classmethod
    def _from_tiled(cls, ring_b, til, pos, count, steps, stale, batch):
        st = cls.__new__(cls)
        st.ring_b, st.pos, st.count, st.steps, st.stale = ring_b, pos, count, steps, stale
        st._std, st._til, st._batch = {}, til, tuple(batch)
        return st

    def _get(self, name):
        a = self._std.get(name)
        if a is None:
            a = self._std[name] = _untile(self._til[name], self._batch)
        return a

    sum_sq = property(lambda self: self._get("sum_sq"))
    sum_b = property(lambda self: self._get("sum_b"))
    jump_run = property(lambda self: self._get("jump_run"))
    excluded = property(lambda self: self._get("excluded"))
    clean_run = property(lambda self: self._get("clean_run"))
    r_est = property(lambda self: self._get("r_est"))

    def _width(self, field="sum_sq"):
        """The last axis of a tiled field (sum_sq: m, the rows; excluded: C, the channels)."""
        a = self._std.get(field)
        return int(a.shape[-1] if a is not None else self._til[field].shape[1])

    def _tiled(self, B):
        """The lane-tiled form (G, k, B) of the tiled fields, B lanes (made once, then kept)."""
        til = self._til
        if til is None or next(iter(til.values())).shape[-1] != B:
            til = self._til = {f: _tile(self._std[f], B) for f in _TILED}
        return til

    def _replace(self, **kw):
        args = [kw.pop(f) if f in kw else getattr(self, f) for f in self._fields]
        if kw:
            raise TypeError(f"MonitorState has no fields {sorted(kw)}")
        return MonitorState(*args)

    def __iter__(self):
        return (getattr(self, f) for f in self._fields)

    def __repr__(self):
        return "MonitorState(" + ", ".join(f"{f}={getattr(self, f)!r}" for f in self._fields[1:]) + ")"

    @property
    def ring(self) -> tuple:
        """The window's beta^2 samples (derived from ``ring_b``: the winsorised beta squared, 1 for a
        missing epoch), slot by slot."""
        return tuple(_sq(b) for b in self.ring_b)

    def take(self, idx) -> MonitorState:
        """The state of batch rows ``idx`` (an index into the first axis; a copy)."""
        return self._replace(ring_b=tuple(a[idx] for a in self.ring_b), sum_sq=self.sum_sq[idx],
                             sum_b=self.sum_b[idx], jump_run=self.jump_run[idx], excluded=self.excluded[idx],
                             clean_run=self.clean_run[idx], r_est=self.r_est[idx],
                             stale=None if self.stale is None else self.stale[idx])

    def merge(self, acc: MonitorState | None, idx, sub: MonitorState) -> MonitorState:
        """The epoch's new state when its batch rows are stepped in parts, each from this state:
        ``acc`` (the parts merged so far; None: none yet) with rows ``idx`` from ``sub``, the state
        ``self.take(idx)`` stepped to. Rows no part stepped keep their values (their window slot
        too). The first call copies what the parts write (this state is not modified); later calls
        write into ``acc``, which must come from an earlier call."""
        p = self.pos
        if acc is None:
            ring_b = list(self.ring_b)
            ring_b[p] = np.array(self.ring_b[p])
            acc = self._replace(ring_b=tuple(ring_b), sum_sq=self.sum_sq.copy(), sum_b=self.sum_b.copy(),
                                jump_run=self.jump_run.copy(), excluded=self.excluded.copy(),
                                clean_run=self.clean_run.copy(), r_est=self.r_est.copy(),
                                stale=None if self.stale is None else self.stale.copy())
        acc.ring_b[p][idx] = sub.ring_b[p]
        for f in ("sum_sq", "sum_b", "jump_run", "excluded", "clean_run", "r_est"):
            getattr(acc, f)[idx] = getattr(sub, f)
        acc._til = None  # (written in its plain form)
        stale = acc.stale
        if sub.stale is not None or stale is not None:
            if stale is None:
                stale = np.zeros(acc.sum_sq.shape, dtype=np.int32)
            stale[idx] = 0 if sub.stale is None else sub.stale
        return acc._replace(pos=sub.pos, count=sub.count, steps=sub.steps, stale=stale)


def _sq(b):
    """beta^2 of winsorised ring samples (NaN, a missing epoch: 1)."""
    return np.where(np.isnan(b), 1.0, b * b)


def _lin(b):
    """beta of winsorised ring samples (NaN, a missing epoch: 0)."""
    return np.where(np.isnan(b), 0.0, b)


def _readmitted_rows(readmit, ch, C):
    """(trial, row) index pairs of every row of a readmitted channel (readmit (..., C), flat trials)."""
    fi = np.flatnonzero(readmit)
    t_ch, c_ch = np.divmod(fi, C)
    k, j = np.nonzero(ch[None, :] == c_ch[:, None])  # (readmission, row of its channel)
    return t_ch[k], j


def _fresh_windows(stale, fr, shape, steps, W):
    """The stale marks after epoch ``steps``: rows ``fr`` (flat (trial, row) indices; None: no
    readmission) fresh until epoch steps + W (on a copy; a new array of ``shape`` when there was
    none); None once every fresh window has filled (checked every W epochs)."""
    if fr is not None:
        stale = np.zeros(shape, dtype=np.int32) if stale is None else stale.copy()
        stale.reshape(-1)[fr] = steps + W
    elif stale is not None and steps % W == 0 and stale.max() <= steps:
        stale = None
    return stale


def _resum(ring_b, stale, pos, steps, W):
    """The window sums (sum_sq, sum_b) recomputed from the ring, after the epoch that wrote slot pos
    (slot i leaves at epoch steps + rel_i: stale while that is < ``stale``)."""
    rb = np.stack(ring_b)
    if stale is not None:
        rel = (np.arange(W) - (pos + 1)) % W + steps
        rb = np.where(rel.reshape((W,) + (1,) * stale.ndim) < stale, np.nan, rb)
    return np.add.reduce(_sq(rb), axis=0), np.add.reduce(_lin(rb), axis=0)


RESUM = 4096
_NONE_M = np.empty((0, 0))  # placeholders for the kernel's unused outputs
_NONE_P = np.empty((0, 0, 0))
_NONE_V = np.empty(0)
_NONE_I = np.empty((0, 0), dtype=np.int32)
_NONE_B = np.empty((0, 0), dtype=bool)  # epochs between exact recomputations of the running window sums


@dataclass
class _Lazy:
    """What a compiled epoch's Report derives its fields from when they are read (Report._derived)."""

    sums: list  # [sum_sq, sum_b]: lane-tiled until ``untiled``, then (..., m) with the patch applied
    untiled: bool
    count: int
    window: int
    huber_c: float | None
    patch: tuple | None
    jump_sigma: float
    thr_ss: float
    thr_bs: float
    batch: tuple
    ex_new: np.ndarray
    ex_old: np.ndarray


class Report:
    """The statistics and verdicts of one monitored epoch (fields as a NamedTuple's: attribute
    access, iteration in this order, ``_replace``):

    beta (..., m) normalised innovations at the prior; jump (..., m) bool: |beta| >= jump_sigma;
    drift_stat (..., m) windowed mean of beta^2; bias_stat (..., m) (windowed sum of beta)^2 / k;
    drift (..., m) bool: either window statistic above its tolerance; used (..., m) bool: the row
    entered the update; weight (..., m) Huber weight of the row (1 inside the threshold, 0 if
    unused); excluded (..., C) bool after this epoch; newly_excluded (..., C) bool; readmitted
    (..., C) bool.

    The compiled monitor does not write jump, drift, drift_stat, bias_stat and weight: they are
    derived on first access from beta and the window sums the epoch's tests saw, with the same
    arithmetic as the numpy reference (jump and drift: the very comparisons the monitor made, on
    the same floats). A caller that reads them pays for them; the monitored step does not."""

    _fields = ("beta", "jump", "drift_stat", "bias_stat", "drift", "used", "weight", "excluded", "newly_excluded",
               "readmitted")
    __slots__ = ("beta", "_jump", "_drift_stat", "_bias_stat", "_drift", "used", "_weight", "_excluded",
                 "newly_excluded", "_readmitted", "_lazy")

    def __init__(self, beta, jump, drift_stat, bias_stat, drift, used, weight, excluded, newly_excluded, readmitted):
        self.beta, self._jump, self._drift, self.used = beta, jump, drift, used
        self._drift_stat, self._bias_stat, self._weight = drift_stat, bias_stat, weight
        self._excluded, self.newly_excluded, self._readmitted = excluded, newly_excluded, readmitted
        self._lazy = None

    @classmethod
    def _derived(cls, beta, used, ex_new, ex_old, newly, sum_sq, sum_b, count, window, huber_c, patch,
                 jump_sigma, thr_ss, thr_bs, batch):
        """A Report whose jump and drift flags, window statistics, weights, excluded and readmitted
        channels come when read from beta, the lane-tiled sums (sum_sq, sum_b) and the lane-tiled
        exclusions after and before the epoch (ex_new, ex_old) (MonitorState._tiled): a channel is
        readmitted when it was out and is in (in every isolation mode; with isolation off nothing
        is ever out); ``patch`` (flat (trial, row) index, sum_sq, sum_b): the sums the tests saw
        where they have since been reset (readmitted rows); thr_ss, thr_bs: the window tests'
        tolerances on the sums (IntegrityMonitor.step); batch: the batch shape."""
        r = cls(beta, None, None, None, None, used, None, None, newly, None)
        r._lazy = _Lazy(sums=[sum_sq, sum_b], untiled=False, count=int(count), window=int(window), huber_c=huber_c,
                        patch=patch, jump_sigma=jump_sigma, thr_ss=thr_ss, thr_bs=thr_bs, batch=tuple(batch),
                        ex_new=ex_new, ex_old=ex_old)
        return r

    @property
    def excluded(self):
        if self._excluded is None:
            self._excluded = _untile(self._lazy.ex_new, self._lazy.batch)
        return self._excluded

    @property
    def readmitted(self):
        if self._readmitted is None:
            self._readmitted = _untile(self._lazy.ex_old, self._lazy.batch) & ~self.excluded
        return self._readmitted

    @property
    def jump(self):
        if self._jump is None:
            self._jump = np.abs(self.beta) >= self._lazy.jump_sigma  # (a missing row has beta = 0)
        return self._jump

    @property
    def drift(self):
        if self._drift is None:
            ss, sb = self._sums(0), self._sums(1)
            self._drift = (ss > self._lazy.thr_ss) | (sb * sb > self._lazy.thr_bs)
        return self._drift

    def _sums(self, i):
        """The window sum i (0: of beta^2, 1: of beta) the epoch's tests saw, (..., m)."""
        lz = self._lazy
        if not lz.untiled:  # untiled (and patched) once
            for k in (0, 1):
                a = _untile(lz.sums[k], lz.batch)
                if lz.patch is not None:
                    a.reshape(-1)[lz.patch[0]] = lz.patch[1 + k]
                lz.sums[k] = a
            lz.untiled = True
        return lz.sums[i]

    @property
    def drift_stat(self):
        if self._drift_stat is None:
            count, W = self._lazy.count, self._lazy.window
            ss = self._sums(0)
            self._drift_stat = ss / W if count == W else (ss - (W - count)) / count  # unfilled slots hold 1
        return self._drift_stat

    @property
    def bias_stat(self):
        if self._bias_stat is None:
            count = self._lazy.count
            sb = self._sums(1)
            self._bias_stat = sb * sb / count  # unfilled slots hold 0
        return self._bias_stat

    @property
    def weight(self):
        if self._weight is None:
            c = self._lazy.huber_c
            w = np.ones_like(self.beta)
            if c is not None:
                ab = np.abs(self.beta)
                w = np.where(ab > c, c / np.maximum(ab, 1e-300), 1.0)
            self._weight = np.where(self.used, w, 0.0)
        return self._weight

    def __iter__(self):
        return (getattr(self, f) for f in self._fields)

    def __len__(self):
        return len(self._fields)

    def _replace(self, **kw):
        return Report(**{f: kw.pop(f, getattr(self, f)) for f in self._fields}, **kw)

    def __repr__(self):
        return "Report(" + ", ".join(f"{f}={getattr(self, f)!r}" for f in self._fields) + ")"


class GuardedModel:
    """A measurement model with rows made inert (``inert`` (..., m) bool: h = z, H = 0) and
    R_jj scaled by ``r_scale`` (..., m) (>= 1: down-weighting), optionally floored by
    ``r_floor`` (..., m). Works for the EKF (h_and_H) and for sigma points (h on (K, ..., n):
    the batch axes align on the right)."""

    def __init__(self, base: MeasurementModel, z, inert, r_scale=None, r_floor=None, prepared=None, r_diag=None):
        self.base = base
        self.z = np.asarray(z, dtype=float)
        self.inert = np.asarray(inert, dtype=bool)
        self.r_scale = r_scale
        self.r_floor = r_floor
        # (x, h, H) already guarded at x (the monitor linearised there): returned for that very x
        self._prepared = prepared
        self._r_diag = r_diag  # the R diagonal to use as it is (floor and scale already applied)

    def h(self, x):
        if self._prepared is not None and x is self._prepared[0]:
            return self._prepared[1]
        return np.where(self.inert, self.z, self.base.h(x))

    def H(self, x):
        return self.h_and_H(x)[1]

    def h_and_H(self, x):
        if self._prepared is not None and x is self._prepared[0]:
            return self._prepared[1], self._prepared[2]
        hx, H = measure(self.base, x)
        H = np.where(self.inert[..., None], 0.0, H)
        return np.where(self.inert, self.z, hx), H

    def _r(self):
        if self._r_diag is not None:
            return self._r_diag
        rd = self.base.R_diag()
        if rd is None:
            raise ValueError("the integrity monitor needs a measurement model with a diagonal R (R_diag)")
        r = np.asarray(rd, dtype=float)
        if self.r_floor is not None:
            r = np.maximum(r, self.r_floor)
        if self.r_scale is not None:
            r = r * self.r_scale
        return r

    def R_diag(self):
        return self._r()

    def R(self):
        r = self._r()
        return r[..., :, None] * np.eye(r.shape[-1])


@dataclass(frozen=True)
class IntegrityMonitor:
    """The integrity layer; ``channels`` (m,) maps each measurement row to its channel."""

    config: IntegrityConfig = IntegrityConfig()

    def init(self, batch_shape, m: int, n_channels: int) -> MonitorState:
        b = tuple(batch_shape)
        W = self.config.window
        empty = np.full(b + (int(m),), np.nan)  # a fresh window: every slot a missing epoch (1 and 0)
        empty.flags.writeable = False  # shared by every slot of the fresh ring
        return MonitorState((empty,) * W, np.full(b + (int(m),), float(W)), np.zeros(b + (int(m),)), 0, 0,
                            np.zeros(b + (n_channels,), dtype=np.int64), np.zeros(b + (n_channels,), dtype=bool),
                            np.zeros(b + (n_channels,), dtype=np.int64), np.full(b + (int(m),), np.nan), 0)

    def innovations(self, x, P, z, model: MeasurementModel):
        """(nu, a^2, HPH'_jj) at the prior, (..., m) each, by linearisation."""
        hx, H = measure(model, x)
        rd = model.R_diag()
        if rd is None:
            raise ValueError("the integrity monitor needs a measurement model with a diagonal R (R_diag)")
        H = np.asarray(H, dtype=float)
        hph = np.einsum("...mi,...ij,...mj->...m", H, P, H)
        return np.asarray(z, dtype=float) - hx, hph + np.asarray(rd, dtype=float), hph

    def step(self, state: MonitorState, x, P, z, model: MeasurementModel, channels, update=ekf_update,
             **update_kw):
        """One monitored update: (UpdateResult, MonitorState, Report).

        channels: (m,) int in [0, C) with C = state.excluded.shape[-1]. NaN measurements are
        treated as missing (inert this epoch, not counted as a fault). ``update_kw`` go to
        ``update``; a ``backend`` among them also picks the monitor's own kernel ("numba":
        filters/_nbintegrity.py, "numpy": the reference below; None/"auto": the filters' default)."""
        cfg = self.config
        x = np.asarray(x, dtype=float)
        P = np.asarray(P, dtype=float)
        z = np.asarray(z, dtype=float)
        ch = np.asarray(channels)
        m = z.shape[-1]
        C = state._width("excluded")
        if ch.shape != (m,) or not np.issubdtype(ch.dtype, np.integer) or ch.min() < 0 or ch.max() >= C:
            raise ValueError(f"channels must be ({m},) ints in [0, {C}), got {channels!r}")
        if state._batch + (state._width(),) != z.shape:
            raise ValueError(f"the monitor state is for measurements of shape {state._batch + (state._width(),)}, "
                             f"got {z.shape}")
        W = cfg.window
        count = min(state.count + 1, W)
        thr_ms = float(cfg.drift_thresholds()[count - 1])
        thr_b = cfg.bias_threshold()
        # both window tests on the sums themselves: (sum_sq - off0) / den > thr_ms and sum_b^2 / count > thr_b
        # (the compiled monitor, the numpy reference and a Report's derived flags compare the same floats)
        off0, den = (0, W) if count == W else (W - count, count)
        thr_ss, thr_bs = thr_ms * den + off0, thr_b * count
        hx, H = measure(model, x)
        rd = model.R_diag()
        if rd is None:
            raise ValueError("the integrity monitor needs a measurement model with a diagonal R (R_diag)")
        old = state.ring_b[state.pos]  # the samples leaving the window
        pos = state.pos
        steps = state.steps + 1
        stale = state.stale
        if _use_kernel(update_kw.get("backend")):
            res, (beta, used, newly, new_b), til0, til, n_readmit, B = self._epoch_kernel(
                state, x, P, z, model, hx, H, rd, ch, thr_ss, thr_bs, old, update, update_kw)
            ex0, ex1 = til0["excluded"], til["excluded"]  # (a readmitted channel: out before, in now)
            ring_b = state.ring_b[:pos] + (new_b,) + state.ring_b[pos + 1:]
            sum_sq_ep, sum_b_ep = til["sum_sq"], til["sum_b"]  # the sums the epoch's tests saw (until a reset)
            patch = None
            if n_readmit:
                g, c_ch, lane = np.nonzero(ex0 & ~ex1)
                k, j = np.nonzero(ch[None, :] == c_ch[:, None])  # (readmission, row of its channel)
                g, lane = g[k], lane[k]
                t = g * B + lane
                ti = (g * m + j) * B + lane  # (trial, row) in the lane-tiled sums
                ssf, sbf = sum_sq_ep.reshape(-1), sum_b_ep.reshape(-1)
                patch = (t * m + j, ssf[ti], sbf[ti])
                ssf[ti] = float(W)
                sbf[ti] = 0.0
            stale = _fresh_windows(stale, None if patch is None else patch[0], z.shape, steps, W)
            if steps % RESUM == 0:  # the running sums, exactly again (rounding does not pile up)
                ss, sb = _resum(ring_b, stale, pos, steps, W)
                til = dict(til, sum_sq=_tile(ss, B), sum_b=_tile(sb, B))
            new_state = MonitorState._from_tiled(ring_b, til, (pos + 1) % W, count, steps, stale, z.shape[:-1])
            # the statistics and weights from the epoch's sums and beta when read
            report = Report._derived(beta, used, ex1, ex0, newly, sum_sq_ep, sum_b_ep, count, W,
                                     cfg.huber_c, patch, cfg.jump_sigma, thr_ss, thr_bs, z.shape[:-1])
            return res, new_state, report
        if state.stale is not None:  # slots of a fresh window leave as the healthy values they stand for
            old = np.where(state.stale > state.steps, np.nan, old)
        (z_f, beta, jump, drift_stat, bias_stat, drift, inert, w, r_used, new_b, sum_sq, sum_b, hx_g,
         H_g, r_est, excluded, newly, readmit, jump_run, clean_run) = self._epoch_numpy(
            state, x, P, z, hx, H, rd, ch, C, count, thr_ss, thr_bs, old)
        gm = GuardedModel(model, z_f, inert, prepared=(x, hx_g, H_g), r_diag=r_used)
        res = update(x, P, z_f, gm, **update_kw)
        ring_b = state.ring_b[:pos] + (new_b,) + state.ring_b[pos + 1:]
        fr = None
        if cfg.isolate and readmit.any():
            # a readmitted channel starts a fresh window of healthy values (beta^2 = 1, beta = 0): its
            # sums are reset and its W ring slots are marked stale until epoch steps + W (no copy of the
            # ring). Readmissions are few: the rows are set by index, in place (sum_sq and sum_b are
            # this epoch's own arrays; the Report has the statistics its tests saw)
            t, j = _readmitted_rows(readmit, ch, C)
            fr = t * m + j
            sum_sq.reshape(-1)[fr] = float(W)
            sum_b.reshape(-1)[fr] = 0.0
        stale = _fresh_windows(stale, fr, z.shape, steps, W)
        if steps % RESUM == 0:
            sum_sq, sum_b = _resum(ring_b, stale, pos, steps, W)
        new_state = MonitorState(ring_b, sum_sq, sum_b, (pos + 1) % W, count, jump_run, excluded, clean_run,
                                 r_est, steps, stale)
        report = Report(beta, jump, drift_stat, bias_stat, drift, ~inert, w, excluded, newly, readmit)
        return res, new_state, report

    def _epoch_kernel(self, state, x, P, z, model, hx, H, rd, ch, thr_ss, thr_bs, old, update, update_kw):
        """The epoch on the compiled kernel (filters/_nbintegrity.py): (UpdateResult, the Report's
        arrays and the new ring slot, the old and the new lane-tiled state (MonitorState._tiled),
        number of readmissions, lanes). Wrapping the EKF update (``ekf_update``), the kernel runs the
        update itself on each block of trials right after the monitor (fused: one pass over P and H);
        any other update runs afterwards on a GuardedModel."""
        from . import _nbintegrity, kernels

        cfg = self.config
        batch = z.shape[:-1]
        m = z.shape[-1]
        n = x.shape[-1]
        N = math.prod(batch)
        one = batch == (N,)  # a flat batch: no reshaping to and fro
        B = max(1, min(N, _nbintegrity.LANES))
        til = state._tiled(B)
        G, C = til["excluded"].shape[:2]

        def flat(a, shape, dtype=float):
            a = np.asarray(a, dtype=dtype)
            if a.shape != batch + shape or not a.flags.c_contiguous or not a.flags.writeable:
                # (a read-only input is copied too: one compiled variant of the kernel, not one per flag)
                a = np.array(np.broadcast_to(a, batch + shape), order="C")
            return a if one else a.reshape((N,) + shape)

        def rows(a):  # (1, m) when shared by every trial, else (N, m)
            a = np.asarray(a, dtype=float)
            return np.array(a, order="C").reshape(1, m) if a.ndim <= 1 else flat(a, (m,))

        fuse = update is ekf_update and set(update_kw) <= {"backend"}
        Ha = np.asarray(H)
        if fuse:  # the fused kernel masks H on its own copy of each lane group: H is only read
            Hk = flat(Ha, (m, n))
        elif Ha.dtype == np.float64 and Ha.shape == batch + (m, n) and Ha.flags.c_contiguous and Ha.flags.writeable:
            # H is masked in place when it is the model's own fresh, writeable array of the full shape
            # (a model must not hand out an H it keeps and reuses: filters/models.py's never do);
            # a shared or read-only H (e.g. LinearGaussian's broadcast view) is copied
            Hk = Ha.reshape(N, m, n)
        else:
            Hk = np.array(np.broadcast_to(Ha, batch + (m, n)), dtype=float, order="C").reshape(N, m, n)
        has_stale = state.stale is not None
        adapt = bool(cfg.adapt_r)

        def fm():
            return np.empty((N, m))

        def bm():
            return np.empty((N, m), dtype=bool)

        def bc(dtype=bool):
            return np.empty((N, C), dtype=dtype)

        def tm(k, dtype=float):
            return np.empty((G, k, B), dtype=dtype)

        beta, y, new_b = fm(), fm(), fm()
        used = bm()
        newly = bc()
        new = {"sum_sq": tm(m), "sum_b": tm(m), "r_est": tm(m) if adapt else til["r_est"],
               "jump_run": tm(C, np.int64), "clean_run": tm(C, np.int64), "excluded": tm(C, bool)}
        # for a guarded model: z without NaN, h, the row mask and R (the fused update keeps them in its lanes)
        z_f = hx_g = r_used = _NONE_M
        inert = _NONE_B
        if not fuse:
            z_f, hx_g, r_used, inert = fm(), fm(), fm(), bm()
        xf, Pf = flat(x, (n,)), flat(P, (n, n))
        xo, Po, nis = (np.empty((N, n)), np.empty((N, n, n)), np.empty(N)) if fuse else (_NONE_M, _NONE_P, _NONE_V)
        prm = np.array([cfg.jump_sigma, thr_ss, thr_bs, cfg.huber_c or 0.0, cfg.r_forget])
        iprm = np.array([cfg.persist, cfg.readmit_after, cfg.huber_c is not None, adapt, cfg.isolate, has_stale,
                         cfg.min_channels, state.steps], dtype=np.int64)
        drive = _nbintegrity.epoch_par if N >= kernels.PARALLEL_MIN_TRIALS else _nbintegrity.epoch_ser
        n_readmit = drive(
            flat(z, (m,)), flat(hx, (m,)), Hk, Pf, rows(rd), til["r_est"], flat(old, (m,)),
            flat(state.stale, (m,), np.int32) if has_stale else _NONE_I, til["sum_sq"], til["sum_b"],
            til["jump_run"], til["excluded"], til["clean_run"], ch.astype(np.int64), prm, iprm,
            beta, inert, used, r_used, y, new_b, new["sum_sq"], new["sum_b"],
            new["r_est"] if adapt else _NONE_P, newly, new["jump_run"], new["clean_run"],
            new["excluded"], z_f, hx_g, fuse, xf, xo, Po, nis, B)

        def shaped(a):
            return a if one else a.reshape(batch + a.shape[1:])

        if fuse:
            res = UpdateResult(shaped(xo), shaped(Po), shaped(y), nis.reshape(batch))
        else:
            gm = GuardedModel(model, shaped(z_f), shaped(inert), prepared=(x, shaped(hx_g), Hk.reshape(batch + (m, n))),
                              r_diag=shaped(r_used))
            res = update(x, P, shaped(z_f), gm, **update_kw)
        arrays = tuple(shaped(a) for a in (beta, used, newly, new_b))
        return res, arrays, til, new, int(n_readmit), B

    def _epoch_numpy(self, state, x, P, z, hx, H, rd, ch, C, count, thr_ss, thr_bs, old):
        """The reference of the compiled monitor (filters/_nbintegrity.py; same outputs)."""
        cfg = self.config
        W, J = cfg.window, cfg.jump_sigma
        missing = ~np.isfinite(z)
        z_f = np.where(missing, 0.0, z)
        H = np.asarray(H, dtype=float)
        hph = np.einsum("...mi,...ij,...mj->...m", H, P, H)
        nu = z_f - hx
        r_nom = np.broadcast_to(np.asarray(rd, dtype=float), nu.shape)
        r_floor = r_nom
        if cfg.adapt_r:
            r_floor = np.where(np.isfinite(state.r_est) & (state.r_est > r_nom), state.r_est, r_nom)
        beta = np.where(missing, 0.0, nu / np.sqrt(hph + r_floor))
        jump = (np.abs(beta) >= J) & ~missing
        # window sums (jump epochs enter winsorised at J, missing ones as the healthy 1 and 0)
        new_b = np.where(missing, np.nan, np.clip(beta, -J, J))
        sum_sq = state.sum_sq + _sq(new_b) - _sq(old)
        sum_b = state.sum_b + _lin(new_b) - _lin(old)
        drift_stat = sum_sq / W if count == W else (sum_sq - (W - count)) / count  # unfilled slots hold 1
        bias_stat = sum_b * sum_b / count  # unfilled slots hold 0
        drift = (sum_sq > thr_ss) | (sum_b * sum_b > thr_bs)

        onehot = ch[:, None] == np.arange(C)[None, :]  # (m, C)

        def any_ch(rows):
            return (rows[..., :, None] & onehot).any(axis=-2)

        jump_ch = any_ch(jump)
        drift_ch = any_ch(drift)
        jump_run = np.where(jump_ch, state.jump_run + 1, 0)
        fault_ch = drift_ch | (jump_run >= cfg.persist)
        excluded = state.excluded
        clean = ~(jump_ch | (drift_ch & ~excluded))  # out: the window tests do not apply
        clean_run = np.where(clean, state.clean_run + 1, 0)
        newly = fault_ch & ~excluded
        if cfg.isolate:
            was = excluded
            readmit = was & (clean_run >= cfg.readmit_after)
            excluded = (was | fault_ch) & ~readmit
            # the isolation mode of each member: 2 rows and channels left out, 1 only the excluded
            # channels (jumped rows used), 0 detect only -- the most that leaves min_channels present
            # channels in
            present = any_ch(~missing)
            n_in = (present & ~excluded).sum(axis=-1)
            n_full = (present & ~excluded & ~jump_ch).sum(axis=-1)
            k = cfg.min_channels
            mode = np.where(n_full >= k, 2, np.where(n_in >= k, 1, 0))
            off = (mode == 0)[..., None]
            readmit = np.where(off, was, readmit)
            newly = np.where(off, fault_ch, newly)
            excluded = excluded & ~off
            inert = missing | excluded[..., ch] | (jump & (mode == 2)[..., None])
        else:
            readmit = np.zeros_like(excluded)
            excluded = np.zeros_like(excluded)
            newly = fault_ch
            inert = missing
        w = np.ones_like(beta)
        r_used = r_floor
        if cfg.huber_c is not None:
            ab = np.abs(beta)
            w = np.where(ab > cfg.huber_c, cfg.huber_c / np.maximum(ab, 1e-300), 1.0)
            r_used = np.where(inert, r_floor, r_floor * (1.0 / np.where(inert, 1.0, w)))
        w = np.where(inert, 0.0, w)
        hx_g = np.where(inert, z_f, hx)
        H_g = np.where(inert[..., None], 0.0, H)
        r_est = state.r_est
        if cfg.adapt_r:
            sample = nu * nu - hph
            lam = cfg.r_forget * (r_nom / (hph + r_nom)) ** 2  # the sample's precision against one at a known prior
            upd = (1.0 - lam) * np.where(np.isfinite(r_est), r_est, r_nom) + lam * sample
            r_est = np.where(inert, r_est, upd)
        return (z_f, beta, jump, drift_stat, bias_stat, drift, inert, w, np.array(r_used, dtype=float), new_b,
                sum_sq, sum_b, hx_g, H_g, r_est, excluded, newly, readmit, jump_run, clean_run)


def _use_kernel(backend) -> bool:
    """The compiled monitor kernel: numba installed and the backend (or the default) is numba."""
    from . import kernels

    if not kernels.HAVE_NUMBA:
        return False
    return kernels.resolve_backend(backend) == "numba"
