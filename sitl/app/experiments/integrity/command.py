"""`skyfuse experiment integrity`: its options (declared once, sitl.params), the scenario of the
command line and the command itself."""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from sitl.app.args import OUTPUT_DIR
from sitl.app.experiments.common import prepare_out, progress_printer
from sitl.app.experiments.integrity.monte_carlo import run
from sitl.app.experiments.integrity.report import plot, result_document, summary
from sitl.app.experiments.integrity.scenario import IntegrityScenario
from sitl.params import (
    add_flags, backend_option, choice, default_of, flag_of, integer, number, optional, param, quiet_option, switch,
    validate,
)

__all__ = ["IntegrityOptions", "add_args", "scenario_from_args", "main", "FLAGS", "OPTION_FIELDS"]


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
    res = run(scn, args.trials, args.seed, progress=progress_printer(args.quiet), backend=backend)
    figures = plot(res, scn, out)
    doc = result_document(scn, args.trials, args.seed, res, figures)
    (out / "result.json").write_text(json.dumps(doc, indent=1, allow_nan=False))
    print(summary(res))
    print("wrote " + ", ".join(str(f) for f in [out / "result.json", *figures]))
    return 0
