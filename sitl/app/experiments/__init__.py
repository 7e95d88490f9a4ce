"""The experiments as a Python API.

    from sitl.app import experiments
    r = experiments.run("beacon", uavs=3, trials=20, seed=1)
    r.reproduces_paper, r.cases["constellation"]["rmse_m"], r.out / "result.json"
    r.plot()
    s = experiments.run("sonde", seeds=12, duration=3800)        # a study: SondeSeedStudyResult
    s.checks, s.per_seed[0]["fused_to_relay_only"]

``run(name, **options)`` runs experiment ``name`` (one of ``NAMES``: the `skyfuse experiment`
subcommands) exactly as the command line does -- the keyword arguments are its flags
(``sweep_trials=5`` is ``--sweep-trials 5``, a list ``uav_counts=[3, 5]`` is ``--uav-counts 3,5``,
``True`` a switch), checked by the same declarations, a bad one a ``UsageError`` of one line --
and returns a typed result: a dataclass of the experiment's headline figures, with every figure
of result.json under ``document`` and its provenance (the equivalent command line among it).
The files (result.json, PNG figures) are written to ``out`` (default: a new temporary
directory, kept). ``progress=True`` shows the run's progress on stderr and its summary table on
stdout (default: quiet; the table is kept as ``summary``).

The studies are runs too: ``run("sonde", seeds=N)`` (`--seeds N`: trial 0 of N seeds) returns a
``SondeSeedStudyResult``, ``run("iono-tropo", study="ordering", seeds=N)`` and
``run("iono-tropo", study="adaptive-q")`` an ``IonoTropoOrderingStudyResult`` /
``IonoTropoAdaptiveQStudyResult``, each read from the file the command line writes for it
(result.json, ordering_study.json, adaptive_q_study.json; ``STUDY_FILES``).

This package's modules are the experiments themselves (beacon/, sonde/, integrity/,
ekf_vs_ukf, iono_tropo, network_faults, long_run; common: what they share); importing the
package is light (the experiment is imported when it runs).
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

NAMES = ("ekf-vs-ukf", "iono-tropo", "sonde", "beacon", "integrity", "faults", "long-run")


@dataclasses.dataclass(frozen=True)
class Provenance:
    """Where a result came from (sitl.app.provenance; result.json's ``provenance``)."""

    skyfuse_version: str | None
    git_commit: str | None
    git_dirty: bool | None
    command_line: list
    seed: Any
    scenario_sha256: str | None
    scenario: dict | None
    started_utc: str
    python_version: str
    numpy_version: str | None
    numba_version: str | None


@dataclasses.dataclass(frozen=True)
class ExperimentResult:
    """What every experiment returns: its name, seed and trials, the schema version, where it
    came from, the files it wrote, and the whole result document (result.json) as ``document``."""

    experiment: str
    seed: Any
    trials: int | None
    schema: int
    provenance: Provenance
    out: Path
    figures: list
    document: dict = dataclasses.field(repr=False)
    summary: str = dataclasses.field(default="", repr=False)  # the table the command line prints

    #: the result.json keys this class holds as typed fields of its own (the subclasses add theirs)
    HEADLINE = ()

    @classmethod
    def from_document(cls, doc: dict, out: Path, summary: str = "") -> "ExperimentResult":
        out = Path(out)
        own = {k: doc.get(k) for k in cls.HEADLINE}
        return cls(experiment=doc["experiment"], seed=doc.get("seed"), trials=doc.get("trials"),
                   schema=doc["schema"], provenance=Provenance(**doc["provenance"]), out=out,
                   figures=[out / f for f in doc.get("figures", [])], document=doc, summary=summary, **own)

    @classmethod
    def load(cls, result_json: str | Path, summary: str = "") -> "ExperimentResult":
        """The result of a run from its result.json (written by the command line or by run())."""
        path = Path(result_json)
        doc = json.loads(path.read_text(encoding="utf-8"))
        cls = STUDY_TYPES.get((doc.get("experiment"), doc.get("study"))) or RESULT_TYPES.get(doc.get("experiment"))
        return (cls or ExperimentResult).from_document(doc, path.parent, summary)

    def to_dict(self) -> dict:
        """The result document (result.json's content)."""
        return self.document

    def plot(self, show: bool = False):
        """The run's figures (its PNGs) in one matplotlib Figure, one panel each; ``show``:
        plt.show() it. Returns the Figure (a notebook displays it)."""
        import matplotlib.image as mpimg
        import matplotlib.pyplot as plt

        files = [f for f in self.figures if Path(f).suffix == ".png"]
        if not files:
            raise ValueError(f"{self.experiment}: no figure in {self.out}")
        fig, axes = plt.subplots(len(files), 1, figsize=(12, 7 * len(files)), squeeze=False)
        for ax, f in zip(axes[:, 0], files):
            ax.imshow(mpimg.imread(f))
            ax.set_axis_off()
            ax.set_title(Path(f).name, fontsize=9)
        fig.tight_layout()
        if show:
            plt.show()
        return fig


def _headline(name: str, doc: str, **fields):
    """A result dataclass of ExperimentResult with the typed headline ``fields`` (name: type)."""
    cls = dataclasses.make_dataclass(
        name, [(k, t, dataclasses.field(default=None)) for k, t in fields.items()], bases=(ExperimentResult,),
        frozen=True, namespace={"__doc__": doc, "HEADLINE": tuple(fields), "__module__": __name__})
    return cls


EkfVsUkfResult = _headline(
    "EkfVsUkfResult", "`ekf-vs-ukf` (seed 001): EKF and UKF statistics per step against the PCRB.",
    steps=int, ekf=dict, ukf=dict, pcrb_position_m=list, ekf_ukf_rmse_max_rel_diff=float)
IonoTropoResult = _headline(
    "IonoTropoResult", "`iono-tropo` (seed 000): the three variants' zenith delay estimates.",
    variants=dict, ordering_3_lt_2_lt_1=bool)
SondeResult = _headline(
    "SondeResult", "`sonde` (seed 004): fused vs relay-only vs radar-only RMSE by ground range.",
    by_range_km=list, overall_rmse_m=dict, fused_below_both_in_every_bin=bool, anees=dict)
BeaconResult = _headline(
    "BeaconResult", "`beacon` (seed 002): the beacon located from the UAVs, decomposed vs centralised.",
    uavs=int, duration_s=float, reproduces_paper=bool, cases=dict, by_uav_count=list,
    centralised_vs_decomposed=dict)
IntegrityResult = _headline(
    "IntegrityResult", "`integrity` (seed 003): fault detection and isolation, plain vs adaptive-robust.",
    position_rmse_m=dict, rmse_ratio=dict, detection=dict, targets_met=dict)
FaultsResult = _headline(
    "FaultsResult", "`faults`: network faults on the measurement links against the fault-free baseline.",
    conditions=list, recovery=list, targets=list, checks=list)
LongRunResult = _headline(
    "LongRunResult", "`long-run`: the default scenario's beacon RMSE per window against its PCRB, ANEES.",
    duration_s=float, windows=list, overall=dict, all_windows_pass=bool)

SondeSeedStudyResult = _headline(
    "SondeSeedStudyResult", "`sonde --seeds N`: trial 0 of N seeds, fused vs relay-only vs radar-only per seed "
    "and in each outage, and the study's checks.",
    seeds=list, per_seed=list, overall=dict, during_gnss_outage=dict, during_radar_loss=dict, checks=dict,
    fraction_fused_below_relay_only=float, worst_ratio_to_relay_only=dict)
IonoTropoOrderingStudyResult = _headline(
    "IonoTropoOrderingStudyResult", "`iono-tropo --study ordering`: time to 1 m of the three variants per seed.",
    seeds=list, trials_per_seed=int, per_seed=list, holds_for=int, of=int, pooled_median_time_to_1m_s=dict,
    pooled_ordering_holds=bool, paired_fraction=dict)
IonoTropoAdaptiveQStudyResult = _headline(
    "IonoTropoAdaptiveQStudyResult", "`iono-tropo --study adaptive-q`: eq 7's adaptive process noise on and off, "
    "with the clock modelled right and mismodelled.",
    clock_scale=float, rows=list)

#: (experiment, its document's ``study``) -> the study's result type
STUDY_TYPES = {("sonde", "seeds"): SondeSeedStudyResult, ("iono-tropo", "ordering"): IonoTropoOrderingStudyResult,
               ("iono-tropo", "adaptive-q"): IonoTropoAdaptiveQStudyResult}
#: (experiment, study) -> the file the command line writes its document to (otherwise result.json)
STUDY_FILES = {("iono-tropo", "ordering"): "ordering_study.json", ("iono-tropo", "adaptive-q"): "adaptive_q_study.json"}

RESULT_TYPES = {"ekf-vs-ukf": EkfVsUkfResult, "iono-tropo": IonoTropoResult, "sonde": SondeResult,
                "beacon": BeaconResult, "integrity": IntegrityResult, "faults": FaultsResult,
                "long-run": LongRunResult}


def _subparser(parser, *path):
    import argparse

    p = parser
    for name in path:
        sub = next(a for a in p._actions if isinstance(a, argparse._SubParsersAction))
        p = sub.choices[name]
    p._add_deferred_flags()
    return p


def command_line(name: str, out: str | Path, *, progress: bool = False, **options) -> list[str]:
    """The `skyfuse` arguments equivalent to ``run(name, out=out, **options)``."""
    from sitl.app.args import UsageError
    from sitl.app.cli import build_parser

    if name not in NAMES:
        raise UsageError(f"experiments.run: unknown experiment {name!r} (one of {', '.join(NAMES)})")
    sub = _subparser(build_parser(), "experiment", name)
    actions = {a.dest: a for a in sub._actions if a.option_strings}
    argv = ["experiment", name, "--out", str(out)]
    if not progress and "quiet" in actions:
        argv.append(actions["quiet"].option_strings[0])
    for key, value in options.items():
        a = actions.get(key)
        if a is None or key in ("out", "quiet", "help"):
            raise UsageError(f"experiments.run({name!r}): unknown option {key}= (its options: "
                             f"{', '.join(sorted(k for k in actions if k not in ('out', 'quiet', 'help')))})")
        flag = a.option_strings[-1] if a.option_strings[-1].startswith("--") else a.option_strings[0]
        if value is None:
            continue
        if a.nargs == 0:  # a switch
            if value is True:
                argv.append(flag)
            elif value is not False:
                raise UsageError(f"experiments.run({name!r}): {key}= is a switch: True or False, got {value!r}")
        elif isinstance(value, (list, tuple)):
            argv += [flag, *map(str, value)] if a.nargs not in (None, "?") else [flag, ",".join(map(str, value))]
        else:
            argv += [flag, str(value)]
    return argv


def run(name: str, *, out: str | Path | None = None, progress: bool = False, **options) -> ExperimentResult:
    """Run experiment ``name`` as `skyfuse experiment NAME` does with the flags ``options``; the
    typed result (module doc). Raises sitl.app.args.UsageError (one line) on a bad option."""
    import contextlib
    import io
    import tempfile

    from sitl.app import cli
    from sitl.app.provenance import mark_started

    if out is None:
        out = Path(tempfile.mkdtemp(prefix=f"skyfuse-{name}-"))
    argv = command_line(name, out, progress=progress, **options)
    mark_started(["skyfuse", *argv])  # the provenance's command line: the equivalent command
    args = cli.build_parser().parse_args(argv)
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed) if not progress else contextlib.nullcontext():
        rc = cli._dispatch(args)
    if rc not in (0, None):
        raise RuntimeError(f"experiment {name} ended with status {rc} (see {out})")
    doc_file = STUDY_FILES.get((name, getattr(args, "study", None)), "result.json")
    return ExperimentResult.load(Path(out) / doc_file, summary=printed.getvalue())


__all__ = ["NAMES", "ExperimentResult", "Provenance", "RESULT_TYPES", "STUDY_FILES", "STUDY_TYPES", "command_line",
           "run", *(c.__name__ for c in (*RESULT_TYPES.values(), *STUDY_TYPES.values()))]
