"""`skyfuse experiment faults`: network faults on the measurement links, swept on the
beacon (seed 002) and sonde (seed 004) scenarios in batch mode.

Each condition is one batch run of the scenario over ``sitl.bus.InMemoryTransport`` with a
``sitl.netfault.KeyFaults`` fault layer on the MEASUREMENT keys only (beacon: the UAVs' beacon
measurements to the ground station; sonde: the relayed GNSS and the radar measurements); the
truth and the estimates the ground station publishes are never faulted.  Every link (concrete
key: one UAV's beacon measurements of one trial, one sonde's relay, the radar's track of one
sonde) draws from its own generator, derived from (seed, key): every condition of a scenario
sees the same world (the same trials, the same measurement noise) and the same fault draws
(common random numbers: 20 % loss drops a subset of what 30 % drops), so a condition and its
baseline differ by the fault alone.

Faults (netem semantics, ``sitl.netfault`` spec text; times since the run's start):
  * ``loss``: random loss, ``loss=P``;
  * ``burst_loss``: Gilbert-Elliott (``gemodel=p,r,100%,0%``: every packet lost in the bad
    state, none in the good one), mean burst length ``burst_len`` packets (r = 1/burst_len),
    stationary loss p / (p + r) = the value;
  * ``delay_s``: ``delay=D~J distribution=normal`` with jitter J = ``jitter_frac`` x D.  The
    ground station processes whole epochs (1 Hz): a measurement due at t + D is used at the
    first epoch at or after its arrival;
  * ``partition_s``: ``partition=A-(A+L)``, every measurement link down together for L
    seconds from A, after convergence (beacon 150 s, sonde 360 s after launch: after the
    scenario's radar angle-tracking loss, 30-330 s).

Scoring, of what a user sees in real time: at each epoch the estimate the ground station has
published by then (the latest one: one per epoch while it publishes, the last one held if it
stops), against the truth at that epoch; the 3-D position error per trial and epoch.
  * ``rmse_m``: RMS over trials and the scored epochs (beacon after 100 s, sonde after 60 s);
    ``baseline_rmse_m``: the same for the fault-free run of the same seed;
  * ``recovery_s`` (partitions): RMSE over a 10 s window (``window_s``, over the trials too)
    against the same window of the baseline run; the time after the heal from which every
    window, up to the end of the run, is within 2x (``recovery_factor``) the baseline's:
    ``recovery_s`` with the window starting at that time (``[heal + s, heal + s + 10)``), and
    ``recovery_trailing_s`` with the window ending there (``(heal + s - 10, heal + s]``, what a
    running 10 s monitor would say; >= the former).  None: not back within the run.  Beside
    them ``recovery_per_epoch_s`` (a 1-epoch window) and ``ratio_at_heal_epoch``;
  * ``per_trial``: each trial's RMSE against its own baseline (median ratio, trials above 2x):
    one diverged trial dominates a pooled RMSE;
  * ``checks``: one run with duplication (``duplicate_check``): the ground station must
    discard every duplicate once (its count = the injected one) and publish exactly the
    fault-free run's estimates.

result.json: ``conditions`` [{scenario, fault, value, rmse_m, baseline_rmse_m, ratio, spec,
link truth counts (sent / lost / partitioned / duplicated / reordered / delay), the ground
station's own counters}], ``recovery`` [{scenario, partition_s, recovery_s, ...}],
``targets`` (the issue's: beacon RMSE at 20 % random loss within 1.5x baseline; back within
2x baseline <= 30 s after a 30 s partition) with pass/fail, and PNG curves.
"""
from __future__ import annotations

import dataclasses
import math
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from sitl.app.args import OUTPUT_DIR
from sitl.params import (ParamError, add_flags, choice, default_of, integer, number, optional, param, quiet_option,
                         require, string, switch, validate)
from sitl.app.experiments.common import prepare_out, progress_printer, run_label, save_figure, strict, write_result
from sitl.app.report import write_report

# numpy and the components are imported inside the functions: the CLI imports this module to
# build its parser (add_args), and `skyfuse --help` must stay instant
if TYPE_CHECKING:
    import numpy as np

SCENARIOS = ("beacon", "sonde")
FAULTS = ("loss", "burst_loss", "delay_s", "partition_s")
FIGURES = ("faults_loss.png", "faults_delay.png", "faults_recovery.png", "faults_partition_error.png")
BEACON_CASE = "three_satellites"  # the seed's case (experiment beacon's first), printed geometry, 3 UAVs
BEACON_UAVS = 3
OUTLIER_FACTOR = 5.0  # a baseline trial this many times the median trial's RMSE has diverged
LOSS_TARGET = {"scenario": "beacon", "fault": "loss", "value": 0.2, "max_ratio": 1.5}
RECOVERY_TARGET = {"partition_s": 30.0, "max_recovery_s": 30.0}


def _levels(hi: float, what: str):
    """A check: a tuple of fault levels, each in (0, hi) (loss fractions, hi = 1) or (0, hi] (what
    says which); stored as a tuple of floats."""
    closed = hi != 1.0

    def check(key, value):
        try:
            levels = tuple(value)
            ok = all(not isinstance(v, bool) and 0.0 < v and (v <= hi if closed else v < hi) for v in levels)
        except TypeError:
            ok = False
        if not ok:
            raise ParamError(key, f"expected {what}, got {value!r}")
        return tuple(float(v) for v in levels)

    return check


@dataclass(frozen=True)
class Plan:
    """The sweep: fault levels (0 = the baseline, always run), and the recovery criterion."""

    loss: tuple = param((0.1, 0.2, 0.3, 0.5), check=_levels(1.0, "loss fractions in (0, 1)"),
                        doc="random (Bernoulli) packet loss levels, fractions of the packets")
    burst_loss: tuple = param((0.1, 0.2, 0.3, 0.5), check=_levels(1.0, "loss fractions in (0, 1)"),
                              doc="burst (Gilbert-Elliott) packet loss levels, stationary fractions of the packets")
    delay_s: tuple = param((0.25, 0.5, 1.0, 2.0), check=_levels(60.0, "delays in (0, 60] s"),
                           doc="packet delay levels, s")
    partition_s: tuple = param((5.0, 10.0, 30.0, 60.0), check=_levels(3600.0, "lengths in (0, 3600] s"),
                               doc="partition lengths (every measurement link cut), s")
    burst_len: float = param(4.0, check=number(1.0, finite=False, what="a burst length >= 1 packet"),
                             doc="mean Gilbert-Elliott burst length, packets (= epochs: one packet per link and epoch)")
    jitter_frac: float = param(0.2, check=number(0.0, what="a fraction in [0, 1]"),
                               doc="delay jitter (normal, sigma) as a fraction of the delay")
    window_s: float = param(10.0, check=number(1.0, finite=False, what="a window >= 1 s"),
                            doc="length of the window over which the recovery after a partition is judged, s")
    recovery_factor: float = param(2.0, check=number(1.0, lo_open=True, finite=False, what="a factor > 1"),
                                   doc="recovered: the windowed error back within this factor of the baseline's")
    duplicate_check: float = param(0.2, check=number(0.0, what="a duplication fraction >= 0"),
                                   doc="one extra run with this packet duplication: no duplicate counted twice "
                                       "(0: none)")
    faults_from_s: float = param(0.0, check=number(0.0, what="a time >= 0"),
                                 doc="loss, burst loss and delay act on packets sent from here, s since the run's "
                                     "start (0: the acquisition included)")

    def __post_init__(self):
        validate(self)
        require(self.jitter_frac <= 1.0, "jitter_frac", f"expected a fraction in [0, 1], got {self.jitter_frac!r}")

    def conditions(self):
        """(fault, value) of every faulty run, in order."""
        return [(f, float(v)) for f in FAULTS for v in getattr(self, f)]


DEFAULT_PLAN = Plan()
QUICK_PLAN = Plan(loss=(0.2, 0.5), burst_loss=(0.2,), delay_s=(1.0,), partition_s=(10.0, 30.0))


@dataclass(frozen=True)
class Setup:
    """A scenario's run: simulated duration, scored epochs, where partitions start."""

    name: str = param(check=choice(*SCENARIOS), doc="the scenario: beacon or sonde")
    duration_s: float = param(check=number(0, lo_open=True), doc="simulated time of every run, s at 1 Hz")
    settle_s: float = param(check=number(0), doc="the errors are scored from here, s since the run's start")
    partition_at_s: float = param(check=number(0), doc="start of every partition, s since the run's start")
    margin_s: float = param(60.0, check=number(0),
                            doc="simulated after the longest partition heals (recovery is judged there), s")

    def __post_init__(self):
        validate(self)

    def check(self, plan: Plan) -> None:
        """The run is long enough for the plan: partitions from partition_at_s up to the plan's longest,
        then margin_s to recover (and faults_from_s inside the run)."""
        need = max(self.partition_at_s + max(plan.partition_s, default=0.0), plan.faults_from_s + 1.0) + self.margin_s
        require(self.duration_s >= need, self.name,
                f"duration {self.duration_s:g} s is too short: partitions from {self.partition_at_s:g} s up to "
                f"{max(plan.partition_s, default=0):g} s long and {self.margin_s:g} s to recover need >= {need:g} s")


SETUPS = {
    "beacon": Setup("beacon", 300.0, 100.0, 150.0),  # the beacon experiment scores after its SETTLE_S = 100 s
    "sonde": Setup("sonde", 600.0, 60.0, 360.0),
}
QUICK_SETUPS = {
    "beacon": Setup("beacon", 250.0, 100.0, 150.0, margin_s=60.0),
    "sonde": Setup("sonde", 460.0, 60.0, 360.0, margin_s=60.0),
}


# ------------------------------------------------------------------ fault specs
def spec_for(fault: str, value: float, plan: Plan, setup: Setup) -> str:
    """The netem-like spec text of one condition (``sitl.netfault.parse_spec``)."""
    if fault == "loss":
        return f"loss={100.0 * value:.6g}%"
    if fault == "burst_loss":
        r = 1.0 / plan.burst_len
        p = value * r / (1.0 - value)  # stationary loss p / (p + r) = value
        if p > 1.0:
            raise ValueError(f"burst_loss {value}: with bursts of {plan.burst_len:g} packets the loss is at most "
                             f"{1.0 / (1.0 + r):.3g}")
        return f"gemodel={100.0 * p:.6g}%,{100.0 * r:.6g}%,100%,0%"
    if fault == "delay_s":
        d, j = value, plan.jitter_frac * value
        return f"delay={1000.0 * d:.6g}ms~{1000.0 * j:.6g}ms distribution=normal" if j > 0 else f"delay={1000.0 * d:.6g}ms"
    if fault == "partition_s":
        a = setup.partition_at_s
        return f"partition={a:.6g}-{a + value:.6g}"
    raise ValueError(f"unknown fault {fault!r}; one of {FAULTS}")


def fault_seed(seed: int) -> int:
    """The seed of a run's KeyFaults (as run_case / run_trials derive it from theirs)."""
    return int(seed) * 1009 + 8


class FaultsFrom:
    """A FaultFilter: ``KeyFaults(rules, seed)`` on the packets sent at ``t >= t_on_s`` (time since
    the run's start); earlier ones pass untouched (and draw nothing)."""

    def __init__(self, rules, seed: int, t_on_s: float):
        from sitl.netfault import KeyFaults

        self.kf = KeyFaults(rules, seed=int(seed))
        self.t_on_s = float(t_on_s)

    def __call__(self, key, payload, t_s):
        return self.kf(key, payload, t_s) if t_s >= self.t_on_s else [(t_s, payload)]

    def truths(self) -> dict:
        return self.kf.truths()


def bus_faults_for(fault: str, spec: str, plan: Plan, seed: int) -> list:
    """A run's bus_faults: the spec on every measurement link, from plan.faults_from_s for the
    loss and delay faults (partitions carry their own times)."""
    if plan.faults_from_s > 0 and fault != "partition_s":
        return [FaultsFrom([("**", spec)], fault_seed(seed), plan.faults_from_s)]
    return [("**", spec)]


# ------------------------------------------------------------------ one run of a scenario
@dataclass
class RunResult:
    t_s: np.ndarray  # (K,) since the run's start
    err2: np.ndarray  # (K, T) squared 3-D error of the estimate a user sees (NaN before the first one)
    fresh: np.ndarray  # (K, T) bool: an estimate was published at that epoch
    link: dict | None  # injected truth summed over the links
    gs: dict  # the ground station's counters
    wall_s: float


def _held(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Forward-fill along axis 0 the rows that hold NaN (no estimate published that epoch):
    what a display shows is the latest estimate. Returns (filled, fresh)."""
    import numpy as np
    fresh = np.all(np.isfinite(x), axis=-1)
    idx = np.where(fresh, np.arange(x.shape[0])[:, None], 0)
    np.maximum.accumulate(idx, axis=0, out=idx)
    out = np.take_along_axis(x, idx[..., None], axis=0)
    out[~np.maximum.accumulate(fresh, axis=0)] = np.nan  # before the first estimate: nothing to show
    return out, fresh


class BeaconRunner:
    """The beacon scenario (experiment beacon's run_case, production locator only, printed
    geometry, BEACON_CASE, BEACON_UAVS UAVs); the world is the same for every condition."""

    def __init__(self, setup: Setup, trials: int, seed: int):
        import numpy as np
        from sitl.app.experiments import beacon as be
        self.be, self.setup, self.trials, self.seed = be, setup, int(trials), int(seed)
        rng = np.random.default_rng([seed, 77, BEACON_UAVS, trials])  # as experiment beacon draws its starts
        self.tracks, self.prior = be.scenario("printed", BEACON_UAVS, setup.duration_s, trials, rng)

    def __call__(self, rules) -> RunResult:
        import numpy as np
        be = self.be
        w0 = time.perf_counter()
        res = be.run_case(BEACON_CASE, self.tracks, self.trials, self.seed, locators=(be.PRODUCTION,),
                          central=False, prior=self.prior, bus_faults=rules)
        x, fresh = _held(res["x"][be.PRODUCTION][..., 0:3])
        e = x - be._truth3(res["truth"])[..., 0:3]
        return RunResult(res["t"], np.sum(e * e, axis=-1), fresh, res["bus_faults"],
                         dict(res["counters"][be.PRODUCTION]), time.perf_counter() - w0)


class SondeRunner:
    """The sonde scenario (experiment sonde's run_trials, the fused tracker only: the ground
    station's product), the seed 004 scenario cut to ``setup.duration_s``."""

    def __init__(self, setup: Setup, trials: int, seed: int):
        from sitl.app.experiments import sonde as so
        self.so, self.setup, self.trials, self.seed = so, setup, int(trials), int(seed)
        self.scn = so.SondeScenario(duration_s=setup.duration_s, white_baseline=False)

    def __call__(self, rules) -> RunResult:
        import numpy as np
        w0 = time.perf_counter()
        raw = self.so.run_trials(self.scn, self.seed, range(self.trials), modes=("fused",), bus_faults=rules)
        pos = np.swapaxes(raw["pos"][0], 0, 1)  # (K, T, 3)
        x, fresh = _held(pos)
        e = x - np.swapaxes(raw["truth_pos"], 0, 1)
        t = raw["t_gps_s"] - raw["t0_gps_s"]
        gs = dict(raw["counters"]["fused"])
        gs["bus_rejected"] = dict(raw["bus"]["rejected"])
        return RunResult(t, np.sum(e * e, axis=-1), fresh, raw.get("bus_faults"), gs, time.perf_counter() - w0)


RUNNERS = {"beacon": BeaconRunner, "sonde": SondeRunner}


# ------------------------------------------------------------------ metrics
def rmse(err2: np.ndarray, sel) -> float | None:
    """RMS over trials and the selected epochs (NaN: no estimate yet, left out)."""
    import numpy as np
    e = err2[sel]
    e = e[np.isfinite(e)]
    return float(math.sqrt(e.mean())) if e.size else None


def per_trial_rmse(err2: np.ndarray, sel) -> np.ndarray:
    """RMS over the selected epochs of each trial (T,) (NaN: a trial without any estimate)."""
    import numpy as np
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.sqrt(np.nanmean(err2[sel], axis=0))


def windowed_mse(err2: np.ndarray, w: int) -> np.ndarray:
    """Mean over the trials and the epochs k .. k+w-1 of err2 (K, T), for each k (NaN where the
    window runs past the end or holds no estimate)."""
    import numpy as np
    K = err2.shape[0]
    ok = np.isfinite(err2)
    s = np.concatenate([[0.0], np.cumsum(np.where(ok, err2, 0.0).sum(axis=1))])
    n = np.concatenate([[0], np.cumsum(ok.sum(axis=1))])
    out = np.full(K, np.nan)
    if K >= w:
        cnt = n[w:] - n[:-w]
        with np.errstate(invalid="ignore", divide="ignore"):
            out[:K - w + 1] = np.where(cnt > 0, (s[w:] - s[:-w]) / np.maximum(cnt, 1), np.nan)
    return out


def _first_stay(r: np.ndarray, factor: float):
    """Smallest s with r[s:] <= factor throughout (NaN counts as not within); None if r[-1] is not."""
    import numpy as np
    bad = ~(r <= factor)
    if not r.size or bad[-1]:
        return None
    return int(np.flatnonzero(bad)[-1]) + 1 if bad.any() else 0


def recovery(t_s, err2, base_err2, heal_s: float, window_s: float, factor: float, dt_s: float = 1.0) -> dict:
    """Recovery after a partition heals at ``heal_s`` (module docstring): the first time s >= 0
    after the heal from which the windowed RMSE stays within ``factor`` x the baseline's over the
    same window up to the end of the run: with the window [heal+s, heal+s+w) (``recovery_s``)
    and (heal+s-w, heal+s] (``recovery_trailing_s``).  Also the peak windowed ratio after the
    heal and the largest error of any trial after it."""
    import numpy as np
    K = err2.shape[0]
    w = max(1, round(window_s / dt_s))
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.sqrt(windowed_mse(err2, w) / windowed_mse(base_err2, w))  # ratio[k]: window [k, k+w)
    h = int(np.searchsorted(t_s, heal_s - 1e-9))
    lead = ratio[h:K - w + 1]  # lead[s]: the window starting at the heal + s
    trail = ratio[max(0, h - w + 1):K - w + 1]  # trail[s]: the window ending at the heal + s (h >= w - 1)
    s_lead, s_trail = _first_stay(lead, factor), _first_stay(trail, factor)
    if h < w - 1 and s_trail is not None:
        s_trail += w - 1 - h  # trail[0] ends at epoch w - 1 > h
    after = err2[h:]
    fin = np.isfinite(after)
    return {
        "recovery_s": None if s_lead is None else s_lead * dt_s,
        "recovery_trailing_s": None if s_trail is None else s_trail * dt_s,
        "peak_window_ratio_after_heal": float(np.nanmax(lead)) if np.isfinite(lead).any() else None,
        "max_error_after_heal_m": float(np.sqrt(after[fin].max())) if fin.any() else None,
    }


def _mse_ratio_at(err2, base_err2, t_s, at_s) -> float:
    """MSE over the trials at the epoch ``at_s`` against the baseline's (squared RMS ratio)."""
    import numpy as np
    k = int(np.searchsorted(t_s, at_s - 1e-9))
    with np.errstate(invalid="ignore", divide="ignore"):
        return float(np.nanmean(err2[k]) / np.nanmean(base_err2[k]))


def _link_counts(link: dict | None) -> dict:
    """The injected truth summed over the links, in the result's words."""
    if not link:
        return {}
    g = link.get
    sent = g("sent", 0)
    out = {"links": g("links", 0), "sent": sent, "delivered": g("delivered", 0), "lost": g("dropped_loss", 0),
           "partitioned": g("dropped_partition", 0), "queue_dropped": g("dropped_queue", 0),
           "duplicated": g("duplicated", 0), "reordered": g("reordered", 0), "corrupted": g("corrupted", 0)}
    if "delay_s_sum" in link and g("delivered", 0):
        out["delay_s_mean"] = g("delay_s_sum") / max(1, g("delivered", 0))
    if "delay_s_max" in link:
        out["delay_s_max"] = g("delay_s_max")
    out["lost_fraction"] = (out["lost"] + out["partitioned"] + out["queue_dropped"]) / sent if sent else None
    return out


# ------------------------------------------------------------------ the sweep
def sweep(scenarios=SCENARIOS, trials: int = 8, seed: int = 1, plan: Plan = DEFAULT_PLAN, setups=None,
          progress=None) -> dict:
    """Run every condition of ``plan`` on each scenario; returns the raw per-scenario results:
    {scenario: {"setup", "baseline": RunResult, "runs": {(fault, value): (spec, RunResult)}}}."""
    setups = dict(SETUPS if setups is None else setups)
    out = {}
    for name in scenarios:
        setup = setups[name]
        setup.check(plan)
        runner = RUNNERS[name](setup, trials, seed)
        t0 = time.perf_counter()
        base = runner(None)
        if progress:
            progress(f"[{name}] baseline: RMSE {rmse(base.err2, base.t_s >= setup.settle_s):.3g} m "
                     f"({trials} trials, {setup.duration_s:g} s; {base.wall_s:.1f} s wall)")
        runs = {}
        conds = plan.conditions()
        for i, (fault, value) in enumerate(conds):
            spec = spec_for(fault, value, plan, setup)
            r = runner(bus_faults_for(fault, spec, plan, seed))
            runs[(fault, value)] = (spec, r)
            if progress:
                sel = r.t_s >= setup.settle_s
                progress(f"[{name}] {i + 1:>2}/{len(conds)} {fault}={value:g} ({spec}): RMSE "
                         f"{rmse(r.err2, sel) or float('nan'):.3g} m; {r.wall_s:.1f} s wall, "
                         f"{time.perf_counter() - t0:.0f} s so far", done=i + 1, total=len(conds))
        checks = {}
        if plan.duplicate_check:
            spec = f"duplicate={100.0 * plan.duplicate_check:.6g}%"
            checks["duplicate"] = (spec, runner([("**", spec)]))
            if progress:
                progress(f"[{name}] check {spec}: {checks['duplicate'][1].wall_s:.1f} s wall")
        out[name] = {"setup": setup, "baseline": base, "runs": runs, "checks": checks}
    return out


def summarise(raw: dict, plan: Plan) -> dict:
    """conditions, recovery, targets and the plot series from sweep()'s output."""
    import numpy as np
    conditions, recov, series, checks, baselines = [], [], {}, [], []
    for name, d in raw.items():
        setup, base = d["setup"], d["baseline"]
        sel = base.t_s >= setup.settle_s
        b = rmse(base.err2, sel)
        pb = per_trial_rmse(base.err2, sel)
        med = float(np.nanmedian(pb)) if np.isfinite(pb).any() else None
        outliers = [int(j) for j in np.flatnonzero(~(pb <= OUTLIER_FACTOR * med))] if med else []
        baselines.append({"scenario": name, "rmse_m": b, "per_trial_rmse_m": pb, "median_trial_rmse_m": med,
                          "outlier_trials": outliers,
                          "note": f"outlier: a trial whose fault-free RMSE exceeds {OUTLIER_FACTOR:g}x the median "
                                  "trial's (a diverged track): it dominates the pooled baseline and every ratio"})
        n_meas = None
        for fault in FAULTS:
            if fault != "partition_s":  # the fault-free point of each curve
                conditions.append({"scenario": name, "fault": fault, "value": 0.0, "rmse_m": b, "baseline_rmse_m": b,
                                   "ratio": 1.0 if b else None, "spec": "none", "link": {}, "ground_station": base.gs,
                                   "epochs_without_fresh_estimate": int((~base.fresh[sel]).sum())})
        ser = {"t_s": base.t_s, "baseline": _rms_series(base.err2), "partitions": {},
               "partition_at_s": setup.partition_at_s, "settle_s": setup.settle_s}
        for (fault, value), (spec, r) in d["runs"].items():
            v = rmse(r.err2, sel)
            row = {"scenario": name, "fault": fault, "value": value, "rmse_m": v, "baseline_rmse_m": b,
                   "ratio": (v / b) if (v is not None and b) else None, "spec": spec, "link": _link_counts(r.link),
                   "ground_station": r.gs, "epochs_without_fresh_estimate": int((~r.fresh[sel]).sum())}
            pt, pb = per_trial_rmse(r.err2, sel), per_trial_rmse(base.err2, sel)
            with np.errstate(invalid="ignore", divide="ignore"):
                q = pt / pb
            row["per_trial"] = {"rmse_m": pt, "baseline_rmse_m": pb, "ratio_median": float(np.nanmedian(q))
                                if np.isfinite(q).any() else None,
                                "trials_above_2x_baseline": int(np.sum(~(q <= 2.0))), "trials": int(q.size)}
            n_meas = row["link"].get("sent", n_meas)
            if fault == "partition_s":
                heal = setup.partition_at_s + value
                after = r.t_s >= heal
                during = (r.t_s >= setup.partition_at_s) & ~after
                row["rmse_during_partition_m"] = rmse(r.err2, during)
                row["baseline_rmse_during_partition_m"] = rmse(base.err2, during)
                row["rmse_after_heal_m"] = rmse(r.err2, after)
                row["baseline_rmse_after_heal_m"] = rmse(base.err2, after)
                rc = recovery(r.t_s, r.err2, base.err2, heal, plan.window_s, plan.recovery_factor)
                r1 = recovery(r.t_s, r.err2, base.err2, heal, 1.0, plan.recovery_factor)
                recov.append({"scenario": name, "partition_s": value, "recovery_s": rc["recovery_s"],
                              "partition_start_s": setup.partition_at_s, "heal_s": heal,
                              "recovery_trailing_s": rc["recovery_trailing_s"],
                              "recovery_per_epoch_s": r1["recovery_s"],
                              "ratio_at_heal_epoch": math.sqrt(_mse_ratio_at(r.err2, base.err2, r.t_s, heal)),
                              "peak_window_ratio_after_heal": rc["peak_window_ratio_after_heal"],
                              "max_error_after_heal_m": rc["max_error_after_heal_m"],
                              "window_s": plan.window_s, "factor": plan.recovery_factor})
                ser["partitions"][value] = _rms_series(r.err2)
            conditions.append(row)
        series[name] = ser
        for kind, (spec, r) in d.get("checks", {}).items():
            lk = _link_counts(r.link)
            gs_dup = r.gs.get("duplicate", r.gs.get("duplicates"))
            same = bool(np.array_equal(r.err2, base.err2, equal_nan=True))
            checks.append({"scenario": name, "check": kind, "spec": spec, "injected_duplicates": lk.get("duplicated"),
                           "ground_station_duplicates": gs_dup, "rmse_m": rmse(r.err2, sel), "baseline_rmse_m": b,
                           "estimates_identical_to_baseline": same,
                           "passed": bool(same and gs_dup == lk.get("duplicated")),
                           "note": "every duplicate discarded once: the GS's duplicate count equals the injected "
                                   "one and the published estimates are bit-identical to the fault-free run's"})
    tg = targets(conditions, recov)
    for t in tg:
        bl = next((x for x in baselines if x["scenario"] == t["scenario"]), None)
        t["baseline_outlier_trials"] = None if bl is None else len(bl["outlier_trials"])
    return {"conditions": conditions, "recovery": recov, "targets": tg, "series": series, "checks": checks,
            "baselines": baselines}


def _rms_series(err2):
    import numpy as np
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.sqrt(np.nanmean(err2, axis=1))


def targets(conditions, recov) -> list[dict]:
    """The issue's targets, each with its measured value and met: True / False / None (not run)."""
    out = []
    lt = LOSS_TARGET
    row = next((c for c in conditions if c["scenario"] == lt["scenario"] and c["fault"] == lt["fault"]
                and abs(c["value"] - lt["value"]) < 1e-9), None)
    out.append({"target": f"{lt['scenario']} RMSE at {100 * lt['value']:g} % random loss within "
                          f"{lt['max_ratio']:g}x the baseline",
                "scenario": lt["scenario"], "measured_ratio": None if row is None else row["ratio"],
                "limit": lt["max_ratio"],
                "per_trial_ratio_median": None if row is None else row.get("per_trial", {}).get("ratio_median"),
                "trials_above_2x_baseline": None if row is None else row.get("per_trial", {}).get(
                    "trials_above_2x_baseline"),
                "met": None if row is None or row["ratio"] is None else bool(row["ratio"] <= lt["max_ratio"])})
    rt = RECOVERY_TARGET
    for r in recov:
        if abs(r["partition_s"] - rt["partition_s"]) < 1e-9:
            v = r["recovery_s"]
            out.append({"target": f"{r['scenario']}: after a {rt['partition_s']:g} s partition heals, back within "
                                  f"{r['factor']:g}x the baseline (RMSE over {r['window_s']:g} s) in <= "
                                  f"{rt['max_recovery_s']:g} s",
                        "scenario": r["scenario"], "measured_recovery_s": v,
                        "measured_recovery_trailing_s": r["recovery_trailing_s"], "limit_s": rt["max_recovery_s"],
                        "met": bool(v is not None and v <= rt["max_recovery_s"]),
                        "met_with_trailing_window": bool(r["recovery_trailing_s"] is not None
                                                         and r["recovery_trailing_s"] <= rt["max_recovery_s"])})
    return out


# ------------------------------------------------------------------ figures
COLORS = {"beacon": "C0", "sonde": "C3"}


def _ratio_scale(ax) -> None:
    """Log scale when the ratios span more than 3x (a diverged run beside unharmed ones), else linear."""
    ys = [y for ln in ax.get_lines() for y in ln.get_ydata() if y == y and y > 0]
    if ys and max(ys) / min(ys) > 3.0:
        ax.set_yscale("log")


def plot(out: Path, summ: dict, meta: str) -> list[Path]:
    import matplotlib
    import numpy as np

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    conds = summ["conditions"]
    scen = list(summ["series"])
    files = []

    def curve(fault, name):
        import numpy as np
        rows = sorted((c for c in conds if c["scenario"] == name and c["fault"] == fault), key=lambda c: c["value"])
        return np.array([c["value"] for c in rows]), np.array([np.nan if c["ratio"] is None else c["ratio"]
                                                               for c in rows])

    # a) RMSE / baseline vs loss, random and bursty
    fig, ax = plt.subplots(figsize=(7.5, 5), constrained_layout=True)
    for name in scen:
        for fault, ls, mk in (("loss", "-", "o"), ("burst_loss", "--", "s")):
            x, y = curve(fault, name)
            if x.size:
                ax.plot(100 * x, y, ls=ls, marker=mk, color=COLORS.get(name), label=f"{name}: "
                        + ("random loss" if fault == "loss" else "Gilbert-Elliott burst loss"))
    ax.axhline(LOSS_TARGET["max_ratio"], color="C2", lw=1.0, ls="-.",
               label=f"target: beacon within {LOSS_TARGET['max_ratio']:g}x at {100 * LOSS_TARGET['value']:g} % loss")
    ax.axvline(100 * LOSS_TARGET["value"], color="C2", lw=0.6, ls=":")
    ax.axhline(1.0, color="k", lw=0.8)
    _ratio_scale(ax)
    ax.set_xlabel("measurement packets lost, % (stationary loss for the bursts)")
    ax.set_ylabel("position RMSE / fault-free RMSE (same seed), ratio")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    ax.set_title(f"Ground-station accuracy against measurement loss\n{meta}", fontsize=9)
    files.append(save_figure(fig, out / FIGURES[0]))

    # b) vs delay
    fig, ax = plt.subplots(figsize=(7.5, 5), constrained_layout=True)
    for name in scen:
        x, y = curve("delay_s", name)
        if x.size:
            ax.plot(x, y, marker="o", color=COLORS.get(name), label=name)
            for xi, yi in zip(x, y):
                ax.annotate(f"{yi:.3f}" if yi < 10 else f"{yi:.3g}", (xi, yi), xytext=(4, 4), textcoords="offset points", fontsize=7,
                            color=COLORS.get(name))
    ax.axhline(1.0, color="k", lw=0.8)
    _ratio_scale(ax)
    ax.set_xlabel("measurement delay, s (normal jitter, sigma = 20 % of the delay); epochs every 1 s")
    ax.set_ylabel("position RMSE / fault-free RMSE (same seed), ratio")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    ax.set_title(f"Ground-station accuracy against measurement delay (out-of-sequence arrivals)\n{meta}", fontsize=9)
    files.append(save_figure(fig, out / FIGURES[1]))

    # c) recovery time vs partition length
    fig, ax = plt.subplots(figsize=(7.5, 5), constrained_layout=True)
    for name in scen:
        rows = sorted((r for r in summ["recovery"] if r["scenario"] == name), key=lambda r: r["partition_s"])
        if not rows:
            continue
        x = np.array([r["partition_s"] for r in rows])
        y = np.array([np.nan if r["recovery_s"] is None else r["recovery_s"] for r in rows])
        yt = np.array([np.nan if r["recovery_trailing_s"] is None else r["recovery_trailing_s"] for r in rows])
        ax.plot(x, y, "o-", color=COLORS.get(name), label=f"{name}: window from that time")
        ax.plot(x, yt, "s:", color=COLORS.get(name), alpha=0.7, label=f"{name}: window up to that time")
        for xi, r in zip(x, rows):
            if r["recovery_s"] is None:
                ax.annotate("not back", (xi, 0), xytext=(0, 6), textcoords="offset points", fontsize=7,
                            color=COLORS.get(name), ha="center")
    ax.plot([RECOVERY_TARGET["partition_s"]], [RECOVERY_TARGET["max_recovery_s"]], marker="v", ms=10, color="C2",
            ls="none", label=f"target: <= {RECOVERY_TARGET['max_recovery_s']:g} s after a "
                             f"{RECOVERY_TARGET['partition_s']:g} s partition")
    ax.set_xlabel("partition length, s (every measurement link down)")
    ax.set_ylabel("time after the heal until the 10 s RMSE stays within 2x baseline, s")
    ax.set_ylim(bottom=-1.0)  # points at 0 s (back at once) stay visible
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(f"Recovery after a partition\n{meta}", fontsize=9)
    files.append(save_figure(fig, out / FIGURES[2]))

    # d) error against time around the partitions
    fig, axes = plt.subplots(len(scen), 1, figsize=(10, 3.8 * max(1, len(scen))), squeeze=False,
                             constrained_layout=True)
    for ax, name in zip(axes[:, 0], scen):
        s = summ["series"][name]
        t, a = s["t_s"], s["partition_at_s"]
        ax.plot(t, s["baseline"], color="k", lw=1.3, label="no fault")
        cmap = plt.get_cmap("viridis")
        parts = sorted(s["partitions"])
        for i, L in enumerate(parts):
            c = cmap(0.15 + 0.7 * i / max(1, len(parts) - 1))
            ax.plot(t, s["partitions"][L], color=c, lw=1.0, label=f"partition {L:g} s")
            ax.axvspan(a, a + L, color=c, alpha=0.08, lw=0)
            ax.axvline(a + L, color=c, lw=0.7, ls=":")
        ax.axvline(s["settle_s"], color="0.5", lw=0.8, ls="--", label="scoring starts")
        ax.set_yscale("log")
        ax.set_xlim(max(0.0, a - 40), t[-1])
        ax.set_ylabel("3-D position error, m\n(RMS over trials)")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7, ncol=3, loc="upper left")
        ax.set_title(f"{name}: real-time estimate's error around a partition from {a:g} s (heal: dotted)", fontsize=9)
    axes[-1, 0].set_xlabel("time since the run's start, s")
    fig.suptitle(meta, fontsize=9)
    files.append(save_figure(fig, out / FIGURES[3]))
    return files


# ------------------------------------------------------------------ the command
TRIALS, QUICK_TRIALS = 8, 3  # Monte Carlo trials per condition, without and with --quick


@dataclass(frozen=True)
class FaultsOptions:
    """`skyfuse experiment faults`'s options, declared once (sitl.params). The burst length and the
    faults' start default to the plan's (Plan); the durations to SETUPS / QUICK_SETUPS."""

    out: Path = param(Path("out/faults"), check=OUTPUT_DIR, metavar="DIR",
                      doc="output directory for result.json and PNG figures")
    trials: int | None = param(None, check=optional(integer(lo=1)), doc="Monte Carlo trials per condition",
                               default_help=f"default {TRIALS}; --quick {QUICK_TRIALS}")
    seed: int = param(1, check=integer(lo=0), doc="seed of the world and the faults")
    duration: float | None = param(None, check=optional(number(0, lo_open=True)), metavar="S",
                                   doc="simulated time of every run, s at 1 Hz; must leave 60 s after the longest "
                                       "partition heals",
                                   default_help="default: " + ", ".join(f"{k} {v.duration_s:g}" for k, v in SETUPS.items())
                                                + "; --quick " + " / ".join(f"{v.duration_s:g}" for v in QUICK_SETUPS.values()))
    scenarios: str = param(",".join(SCENARIOS), check=string(), metavar="NAMES",
                           doc=f"comma-separated scenarios: {', '.join(SCENARIOS)}")
    quick: bool = param(False, check=switch(),
                        doc="fewer levels (loss 20, 50 %; burst 20 %; delay 1 s; partitions 10, 30 s), "
                            f"{QUICK_TRIALS} trials unless --trials, shorter runs")
    faults_from: float = param(default_of(Plan, "faults_from_s"), check=number(0), metavar="S",
                               doc="loss, burst loss and delay act on measurements sent from S s on; partitions keep "
                                   "their own times", note=": from the first epoch, the tracks' acquisition included")
    burst_len: float = param(default_of(Plan, "burst_len"), check=number(0, lo_open=True), metavar="N",
                             doc="mean Gilbert-Elliott burst length, packets")
    quiet: bool = quiet_option()

    __post_init__ = validate


def add_args(p) -> None:
    add_flags(p, FaultsOptions)


def _config(args):
    from sitl.app.args import UsageError

    names = [s.strip() for s in str(args.scenarios).split(",") if s.strip()]
    bad = [s for s in names if s not in SCENARIOS]
    if not names or bad:
        raise UsageError(f"--scenarios: comma-separated names from {', '.join(SCENARIOS)}, got {args.scenarios!r}")
    names = list(dict.fromkeys(names))
    quick = bool(getattr(args, "quick", False))
    try:
        plan = dataclasses.replace(QUICK_PLAN if quick else DEFAULT_PLAN,
                                   burst_len=float(getattr(args, "burst_len", DEFAULT_PLAN.burst_len)),
                                   faults_from_s=float(getattr(args, "faults_from", None) or default_of(Plan, "faults_from_s")))
        for v in plan.burst_loss:
            spec_for("burst_loss", v, plan, SETUPS["beacon"])
    except ValueError as exc:
        flag = "--faults-from" if "faults_from" in str(exc) else "--burst-len"
        raise UsageError(f"{flag}: {exc}") from None
    setups = dict(QUICK_SETUPS if quick else SETUPS)
    if args.duration is not None:
        if not (math.isfinite(args.duration) and args.duration <= 36000.0):
            raise UsageError(f"--duration: at most 36000 s, got {args.duration:g}")
        setups = {k: dataclasses.replace(v, duration_s=float(args.duration)) for k, v in setups.items()}
    for n in names:
        try:
            setups[n].check(plan)
        except ValueError as exc:
            raise UsageError(f"--duration: {exc}") from None
    trials = args.trials if args.trials is not None else (QUICK_TRIALS if quick else TRIALS)
    return names, plan, setups, trials


def run(args) -> dict:
    names, plan, setups, trials = _config(args)
    out = prepare_out(Path(args.out))
    prog = progress_printer(getattr(args, "quiet", False), "faults")
    wall0 = time.perf_counter()
    raw = sweep(names, trials, args.seed, plan, setups, prog)
    summ = summarise(raw, plan)
    wall = time.perf_counter() - wall0
    meta = (run_label("faults", seed=args.seed, trials=trials, extra="per condition") + "\n"
            + ", ".join(f"{n} {setups[n].duration_s:g} s" for n in names)
            + "; faults on the measurement links only"
            + (f", loss and delay from {plan.faults_from_s:g} s" if plan.faults_from_s else ""))
    figs = plot(out, summ, meta)
    doc = result_document(args, names, plan, setups, trials, raw, summ, wall, figs)
    doc = write_result(out / "result.json", doc, seed=args.seed,
                        scenario={"scenarios": doc["scenarios"], "plan": doc["plan"], "trials": trials})
    write_report(out)  # OUT/report.html from result.json (sitl.app.report)
    return doc


def result_document(args, names, plan, setups, trials, raw, summ, wall, figs) -> dict:
    from sitl.app.experiments import beacon as be
    from sitl.app.experiments import sonde as so
    walls = {n: {"baseline": d["baseline"].wall_s, "conditions": sum(r.wall_s for _, r in d["runs"].values())}
             for n, d in raw.items()}
    doc = {
        "experiment": "faults", "schema": None, "seed": args.seed, "trials": trials,
        "quick": bool(getattr(args, "quick", False)),
        "scenarios": {n: {**dataclasses.asdict(setups[n]),
                          "measurement_keys": list(be.MEASUREMENT_KEYS if n == "beacon" else so.MEASUREMENT_KEYS),
                          "what": (f"seed 002 beacon, {BEACON_CASE}, printed geometry, {BEACON_UAVS} UAVs, production "
                                   f"locator ({be.PRODUCTION})" if n == "beacon" else
                                   "seed 004 radiosonde, fused tracker (relayed GNSS + radar)")}
                      for n in names},
        "plan": dataclasses.asdict(plan),
        "scoring": "real time: at each epoch the latest estimate the ground station has published, against the "
                   "truth then; RMS over trials and the epochs from settle_s; recovery: 10 s windows (pooled over "
                   "trials) against the same windows of the fault-free run, first time after the heal from which "
                   "every window to the end of the run is within the factor (recovery_s: window starting then; "
                   "recovery_trailing_s: window ending then)",
        "conditions": summ["conditions"],
        "recovery": summ["recovery"],
        "targets": summ["targets"],
        "checks": summ["checks"],
        "baselines": summ["baselines"],
        "all_targets_met": all(t["met"] for t in summ["targets"]) if summ["targets"] else None,
        "wall_s": wall,
        "wall_s_by_scenario": walls,
        "figures": [f.name for f in figs],
    }
    return strict(doc)


def _gs_late(gs: dict) -> tuple:
    """(late measurements the ground station used, measurements it dropped as too old) from its
    counters (beacon locator: late_accepted, rejected_too_late / rejected_stale; sonde tracker:
    late_accepted, too_late / stale)."""
    used = gs.get("late_accepted")
    old = sum(int(gs.get(k, 0) or 0) for k in ("rejected_too_late", "rejected_stale", "too_late", "stale"))
    return used, old


def table(doc) -> str:
    rows = [(f"{'scenario':<8} {'fault':<12} {'value':>6} {'RMSE m':>10} {'base m':>8} {'ratio':>8} {'med.':>6} "
             f"{'>2x':>3} {'sent':>7} {'lost':>6} {'part.':>6} {'dup':>5} {'reord':>5} {'GS late':>7} {'too old':>7}  spec")]
    rows.append("-" * len(rows[0]))
    for c in doc["conditions"]:
        lk = c.get("link") or {}
        gs = c.get("ground_station") or {}
        late, old = _gs_late(gs)

        def f(v, fmt):
            return "-" if v is None else format(v, fmt)

        pt = c.get("per_trial") or {}
        rows.append(f"{c['scenario']:<8} {c['fault']:<12} {c['value']:>6g} {f(c['rmse_m'], '10.3f')} "
                    f"{f(c['baseline_rmse_m'], '8.3f')} {f(c['ratio'], '8.3f')} {f(pt.get('ratio_median'), '6.2f')} "
                    f"{pt.get('trials_above_2x_baseline', ''):>3} {lk.get('sent', ''):>7} "
                    f"{lk.get('lost', ''):>6} {lk.get('partitioned', ''):>6} {lk.get('duplicated', ''):>5} "
                    f"{lk.get('reordered', ''):>5} {'' if late is None else late:>7} {old:>7}  {c['spec']}")
    for r in doc["recovery"]:
        rows.append(f"recovery {r['scenario']:<7} partition {r['partition_s']:>4g} s (from {r['partition_start_s']:g} s): "
                    f"{'not back' if r['recovery_s'] is None else format(r['recovery_s'], 'g') + ' s'} "
                    f"(trailing window: {'not back' if r['recovery_trailing_s'] is None else format(r['recovery_trailing_s'], 'g') + ' s'}; "
                    f"peak 10 s ratio after heal {r['peak_window_ratio_after_heal'] or float('nan'):.3g}; "
                    f"error ratio at the heal epoch {r['ratio_at_heal_epoch'] or float('nan'):.3g}, per-epoch "
                    f"recovery {'not back' if r['recovery_per_epoch_s'] is None else format(r['recovery_per_epoch_s'], 'g') + ' s'})")
    for c in doc.get("checks", []):
        rows.append(f"check {c['scenario']:<7} {c['spec']}: injected {c['injected_duplicates']} duplicates, ground station "
                    f"counted {c['ground_station_duplicates']}; estimates identical to the fault-free run: "
                    f"{c['estimates_identical_to_baseline']} -> {'PASS' if c['passed'] else 'FAIL'}")
    for bl in doc.get("baselines", []):
        if bl["outlier_trials"]:
            rows.append(f"WARNING {bl['scenario']}: fault-free trial(s) {bl['outlier_trials']} diverged (RMSE > "
                        f"{OUTLIER_FACTOR:g}x the median trial's {bl['median_trial_rmse_m']:.3g} m): the pooled "
                        "baseline and the ratios against it mean little; see the per-trial medians or use more trials")
    for t in doc["targets"]:
        v = t.get("measured_ratio", t.get("measured_recovery_s"))
        extra = ""
        if t.get("per_trial_ratio_median") is not None:
            extra = (f"; median trial ratio {t['per_trial_ratio_median']:.3g}, "
                     f"{t['trials_above_2x_baseline']} trial(s) above 2x")
        rows.append(f"TARGET {'MET' if t['met'] else ('NOT MET' if t['met'] is False else 'NOT RUN')}: {t['target']} "
                    f"(measured {v if v is None else format(v, '.3g')}{extra})")
    rows.append("ratio: pooled RMSE / fault-free RMSE (same seed); med.: median over trials of each trial's ratio; "
                ">2x: trials whose RMSE exceeds twice their own fault-free RMSE; sent / lost / part.(itioned) / dup / "
                "reord: injected truth over the measurement links; GS late: late (out-of-sequence) measurements the "
                "ground station used; too old: those it dropped as older than its lag window")
    rows.append(f"{doc['trials']} trials, seed {doc['seed']}; wall {doc['wall_s']:.1f} s")
    return "\n".join(rows)


def main(args) -> int:
    doc = run(args)
    print(table(doc))
    print(f"wrote {Path(args.out) / 'result.json'} and {', '.join(doc['figures'] + ['report.html'])}")
    return 0
