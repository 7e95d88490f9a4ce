"""`skyfuse experiment integrity`: seed 003, the integrity layer on faulty GNSS data.

World (sitl, truth): a GPS L1 receiver on a vehicle flying a great circle at constant speed
(seed 000's trajectory style: 55 N 37 E, 1 km, 50 m/s, heading 90 deg), 10 Hz, white noise
sigma_pr = 6 m, sigma_prr = 0.064 m/s (seed 000). The channels are the satellites above the
elevation mask all through the run (>= ``MIN_CHANNELS`` so that one faulty channel leaves
redundancy for isolation); a channel is one satellite's pseudorange and rate rows.
Sensor errors (seed 003's model): on top of the white noise, one first-order Gauss-Markov
pseudorange error per satellite (sitl.measfault.GaussMarkov), sigma ``gm_sigma_m`` = 2 m,
tau ``gm_tau_s`` = 100 s: the slowly varying residual of the broadcast ionosphere / troposphere
corrections, the satellite clock and ephemeris (SISRE) and code multipath on a moving
airframe, lumped (typical L1 C/A budgets: iono residual 1-5 m over tens of minutes, SISRE
~1 m over hours, multipath 0.5-2 m over seconds to minutes; 2 m / 100 s sits in between). The
simulated receiver's own atmosphere is switched off (its delays are what this residual
models); the receiver clock is seed 000's TCXO.
Faults (seed 003's instrumental causes; sitl.measfault.FaultInjector, drawn per trial from
the seeded Generator): a step on one random satellite's pseudorange (|magnitude| uniform in
``step_sigma`` x sigma_ref, sigma_ref = sqrt(sigma_pr^2 + gm_sigma^2), random sign, lasting
``step_duration_s``), a pseudorange-only ramp on another satellite (|rate| uniform in
``ramp_rate_m_s``, random sign, to the end of the run), heavy-tailed multipath outliers on
every pseudorange (probability ``outlier_prob`` per epoch, scale sigma_pr x Student-t with
``outlier_dof`` degrees of freedom) and a dropout (both rows of one random satellite missing
for ``dropout_s``); onsets uniform in [``onset_min_s``, ``onset_max_frac`` x duration].

Filters, all on the same faulty data (truth never enters a filter; the satellite states come
from world.ephemeris_for_filter at the measured transit time):
* ``plain``: EKF, PseudorangeDoppler on x = [p(3), clock bias, v(3), clock drift] with a
  constant-velocity + random-walk-clock transition; R = white + GM variance, the GM error
  treated as white noise. Missing rows are skipped (the monitor in detect-only mode, which
  is bitwise the plain filter otherwise).
* ``adaptive_robust``: the same EKF wrapped by filters.integrity.IntegrityMonitor (jump and
  window tests, isolation per channel, Huber weights, innovation-based R) with seed 000's
  eq 7 adaptive Q (filters.adaptive) on the dynamic states.
* ``adaptive_robust_with_bias_estimation``: that plus one GM pseudorange-bias state per
  channel (sigma, tau as the world's: the filter knows the error model, not its values), so
  the slow errors are estimated and compensated rather than treated as white noise; R is
  then the white noise only.
Beside them, on the fault-free data of the same world (before injection): the plain EKF
with and without the monitor (same IntegrityConfig), to show that the monitor costs nothing
when nothing is wrong (``fault_free``: paired per-trial comparison).

Scoring (result.json ``detection`` is the monitor of the adaptive-robust filter with bias
estimation: its model matches the world, so its healthy innovations are white N(0, 1) as the
seed's tests assume; the plain-model adaptive-robust filter's monitor, whose innovations carry
the unmodelled GM errors (correlated over the window: its window tests over-alarm), is beside it
under ``detection_by_filter``): an alarm on a channel-epoch is a jump or window-test alarm on
any of its rows.
* step: detected if an alarm on its channel at the onset epoch or the next;
* ramp: an alarm on its channel within ``ramp_detect_s`` of the onset;
* outlier: outliers of >= 5 sigma_ref (on channels with no step or ramp) alarmed at their epoch;
* pfa: alarms per channel-epoch with no fault of any kind on that channel now or within the
  last ``window`` epochs (the window statistics remember a fault that long), after the
  warm-up; with the exact (Clopper-Pearson) 95 % interval.
* mean_delay_s: over the detected events, onset to the first alarm.
* ramp.oracle (code-only ramps): the bound on any detector, ramp_oracle_pd: the Pd within
  ``ramp_detect_s`` of an oracle that knows the faulty channel, the onset and the receiver's state,
  testing at every epoch at the Pfa target; averaged over the same ramps as ``ramp.pd``.
* position_rmse_m: 3-D position error, RMS over trials and the epochs after the warm-up.
ROC: the statistics of the adaptive-robust run (jump: the channel's max |beta|; window: the
channel's max of bias_stat / its threshold and drift_stat / its threshold) swept over
thresholds offline, Pd per fault kind against Pfa per channel-epoch of that statistic alone;
the operating point (the chosen thresholds) is marked. The sweep is open-loop: the run's
exclusions happened at the operating point.

The package, one concern a module (every public name is re-exported here): ``scenario`` (the
declared IntegrityScenario), ``models`` (the bias states and their measurement), ``monte_carlo``
(the faults' draws and the run), ``scoring`` (detection bookkeeping, ROC, the ramp bound, the
targets) and ``report`` (result.json, figures, summary); the command itself, its options
(declared once, sitl.params) and main, is this module.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from sitl.app.args import OUTPUT_DIR
from sitl.app.experiments.common import prepare_out, progress_printer, write_result
from sitl.app.report import write_report
from sitl.app.experiments.integrity.models import BiasedPseudorangeDoppler, GaussMarkovBank
from sitl.app.experiments.integrity.monte_carlo import (
    BIASED, CLEAN, DETECTION_FILTER, DYNAMIC, FILTERS, K_DROP, K_OUT, K_RAMP, K_STEP, MONITORED, run,
)
from sitl.app.experiments.integrity.monte_carlo import _faults  # noqa: F401  (the tests draw the faults alone)
from sitl.app.experiments.integrity.report import FIGURES, plot, result_document, summary, targets_check
from sitl.app.experiments.integrity.scenario import (
    IDX_BIAS, IDX_DRIFT, MIN_CHANNELS, N_BASE, ORDER, RAMP_KINDS, IntegrityScenario,
)
from sitl.app.experiments.integrity.scoring import J_GRID, TARGETS, W_GRID, ramp_oracle_pd, ramp_signature
from sitl.params import (
    add_flags, backend_option, choice, default_of, flag_of, integer, number, optional, param, quiet_option, switch,
    validate,
)

__all__ = ["IntegrityScenario", "run", "FILTERS", "MIN_CHANNELS", "main", "add_args", "IntegrityOptions",
           "scenario_from_args", "FIGURES", "TARGETS", "targets_check", "result_document", "plot", "summary",
           "ramp_signature", "ramp_oracle_pd", "GaussMarkovBank", "BiasedPseudorangeDoppler", "N_BASE", "IDX_BIAS",
           "IDX_DRIFT", "DETECTION_FILTER", "FLAGS", "OPTION_FIELDS", "BIASED", "CLEAN", "DYNAMIC", "MONITORED",
           "ORDER", "RAMP_KINDS", "J_GRID", "W_GRID", "K_STEP", "K_RAMP", "K_OUT", "K_DROP"]


# ------------------------------------------------------------------ the command's options
def _scn(name):
    return lambda: default_of(IntegrityScenario, name)  # the default a None option stands for


@dataclass(frozen=True)
class IntegrityOptions:
    """`skyfuse experiment integrity`'s options, declared once (sitl.params). A None option keeps
    IntegrityScenario's default (shown in --help); the scenario's checks are usage errors before
    any run."""

    trials: int = param(200, check=integer(lo=1), doc="Monte Carlo trials")
    seed: int = param(3, check=integer(lo=0), doc="seed of the numpy SeedSequence")
    out: Path = param(Path("out/integrity"), check=OUTPUT_DIR, metavar="DIR",
                      doc="output directory for result.json and PNG figures")
    duration: float = param(default_of(IntegrityScenario, "duration_s"), check=number(0, lo_open=True), metavar="S",
                            doc="simulated time, s at 10 Hz; faults start between 60 s and 0.7 x this")
    sigma_pr: float | None = param(None, check=optional(number(0, lo_open=True)), metavar="M",
                                   doc="pseudorange white noise", shown=_scn("sigma_pr_m"))
    sigma_prr: float | None = param(None, check=optional(number(0, lo_open=True)), metavar="M_S", doc="rate noise",
                                    shown=_scn("sigma_prr_m_s"))
    el_mask_deg: float | None = param(None, check=optional(number()), metavar="DEG",
                                      doc="elevation mask in [5, 90); >= 7 satellites must stay in view",
                                      shown=_scn("el_mask_deg"))
    gm_sigma: float | None = param(None, check=optional(number(0)), metavar="M",
                                   doc="Gauss-Markov pseudorange error sigma per satellite", shown=_scn("gm_sigma_m"))
    gm_tau: float | None = param(None, check=optional(number(0, lo_open=True)), metavar="S",
                                 doc="its correlation time", shown=_scn("gm_tau_s"))
    jump_sigma: float | None = param(None, check=optional(number(0, lo_open=True)), metavar="X",
                                     doc="jump test threshold on |beta|", shown=_scn("jump_sigma"))
    window: int | None = param(None, check=optional(integer(lo=1)), doc="window of the drift tests, epochs",
                               shown=_scn("window"))
    window_alpha: float | None = param(None, check=optional(number(0, lo_open=True)), metavar="A",
                                       doc="mean-square test alpha", shown=_scn("window_alpha"))
    bias_alpha: float | None = param(None, check=optional(number(0, lo_open=True)), metavar="A",
                                     doc="bias test alpha", shown=_scn("bias_alpha"))
    huber_c: float | None = param(None, check=optional(number(0, lo_open=True)), metavar="X",
                                  doc="Huber threshold on |beta|", shown=_scn("huber_c"))
    outlier_prob: float | None = param(None, check=optional(number(0)), metavar="P",
                                       doc="outlier probability per pseudorange-epoch", shown=_scn("outlier_prob"))
    ramp_kind: str | None = param(None, check=optional(choice("code", "clock")),
                                  doc="code: the pseudorange alone drifts (no Doppler trace); clock: a satellite clock "
                                      "frequency fault, the pseudorange rate carries the ramp's rate too",
                                  shown=_scn("ramp_kind"))
    no_faults: bool = param(False, check=switch(), doc="the same world with no faults injected")
    backend: str = backend_option("filter kernels")
    quiet: bool = quiet_option()

    __post_init__ = validate


# option -> the scenario field it sets (a None option keeps the scenario's default)
OPTION_FIELDS = {"duration": "duration_s", "sigma_pr": "sigma_pr_m", "sigma_prr": "sigma_prr_m_s",
                 "el_mask_deg": "el_mask_deg", "gm_sigma": "gm_sigma_m", "gm_tau": "gm_tau_s",
                 "jump_sigma": "jump_sigma", "window": "window", "window_alpha": "window_alpha",
                 "bias_alpha": "bias_alpha", "huber_c": "huber_c", "outlier_prob": "outlier_prob",
                 "ramp_kind": "ramp_kind"}
# scenario field -> command-line flag, to name the flag in a usage error (the fault onsets and the
# warm-up must fit in --duration)
FLAGS = {**{field: flag_of(IntegrityOptions, opt) for opt, field in OPTION_FIELDS.items()},
         "onset_min_s": flag_of(IntegrityOptions, "duration"), "warmup_s": flag_of(IntegrityOptions, "duration")}


def add_args(p) -> None:
    add_flags(p, IntegrityOptions)


def scenario_from_args(args) -> IntegrityScenario:
    kw = {"duration_s": args.duration}
    for opt, field in OPTION_FIELDS.items():
        v = getattr(args, opt, None)
        if v is not None:
            kw[field] = v
    if getattr(args, "no_faults", False):
        kw["faults"] = False
    try:
        return IntegrityScenario(**kw)
    except ValueError as exc:
        msg = " ".join(str(exc).split())
        flag = next((f for name, f in FLAGS.items() if msg.startswith((name + " ", name + ":", name + " ="))), None)
        raise ValueError(f"{flag}: {msg}" if flag else msg) from None


def main(args) -> int:
    from sitl.app.args import UsageError

    try:
        scn = scenario_from_args(args)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    out = prepare_out(Path(args.out))
    backend = None if getattr(args, "backend", default_of(IntegrityOptions, "backend")) == "auto" else args.backend
    res = run(scn, args.trials, args.seed, progress=progress_printer(args.quiet, "integrity"), backend=backend)
    figures = plot(res, scn, out)
    write_result(out / "result.json", result_document(scn, args.trials, args.seed, res, figures),
                 seed=args.seed, scenario=scn)
    write_report(out)  # OUT/report.html from result.json (sitl.app.report)
    print(summary(res))
    print("wrote " + ", ".join(str(f) for f in [out / "result.json", *figures, out / "report.html"]))
    return 0
