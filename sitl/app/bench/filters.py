"""`skyfuse bench filters`: batched EKF/UKF time per trial-step against FilterPy.

Everything is measured in the same run on the same seed 001 model (11 states,
4 satellites, 8 measurements per step) and the same simulated measurements:
* skyfuse: one batched step (predict + update, model evaluation included) over N trials,
  divided by N; both kernel backends (compiled numba, plain numpy);
* FilterPy: ExtendedKalmanFilter / UnscentedKalmanFilter (MerweScaledSigmaPoints with
  the seed's kappa + n = 3) stepping one trial, with lean single-trial numpy h(x) and
  H(x) written for it, so the peer is not slowed by our batched model objects.
The figure of merit is the ratio filterpy_s_per_trial_step / skyfuse_s_per_trial_step.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sitl.app.progress import progress_printer
from sitl.app.provenance import options_scenario, write_json
from sitl.app.args import OUTPUT_FILE
from sitl.params import add_flags, choice, integer, optional, param, several, validate

from filters import kernels, models
from filters.ekf import ekf_step
from filters.ukf import SigmaPoints, ukf_predict, ukf_update


def _scenario_data(n_trials, n_steps, seed=7):
    """Measurements and filter-side satellite states of the seed 001 scenario."""
    from sitl.app.experiments.ekf_vs_ukf import EkfVsUkfScenario, Setup

    setup = Setup.make(EkfVsUkfScenario(steps=n_steps))
    zs, sps, svs = [], [], []
    for k, _, _, z, meas, _ in setup.stream(n_trials, np.random.default_rng(seed)):
        if k:
            zs.append(z)
            sps.append(meas.sat_pos_ecef_m)
            svs.append(meas.sat_vel_ecef_m_s)
    return setup.scn, setup.transition, setup.x0, setup.P0, np.array(zs), np.array(sps), np.array(svs)


def _time_skyfuse(kind, backend, scn, trans, x0, P0, zs, sps, svs, n_trials):
    points = SigmaPoints.julier(11)
    x = np.broadcast_to(x0, (n_trials, 11)).copy()
    P = np.broadcast_to(P0, (n_trials, 11, 11)).copy()

    def step(x, P, k):
        meas = models.PseudorangeDoppler(sps[k, :n_trials], svs[k, :n_trials], scn.sigma_pr_m, scn.sigma_prr_m_s)
        if kind == "ekf":
            r = ekf_step(x, P, zs[k, :n_trials], trans, meas, scn.dt_s, backend=backend)
        else:
            xp, Pp = ukf_predict(x, P, trans, scn.dt_s, points=points, backend=backend)
            r = ukf_update(xp, Pp, zs[k, :n_trials], meas, points=points, backend=backend)
        return r.x, r.P

    x, P = step(x, P, 0)  # warm-up (compilation is cached, but first calls still load)
    n_steps = zs.shape[0]
    t0 = time.perf_counter()
    for k in range(1, n_steps):
        x, P = step(x, P, k)
    dt = time.perf_counter() - t0
    return dt / ((n_steps - 1) * n_trials)


def _time_filterpy(kind, scn, trans, x0, P0, zs, sps, svs, n_steps):
    from filterpy.kalman import ExtendedKalmanFilter, MerweScaledSigmaPoints, UnscentedKalmanFilter

    F, Q = trans.F(None, scn.dt_s), trans.Q(scn.dt_s)
    R = np.diag(np.r_[np.full(4, scn.sigma_pr_m**2), np.full(4, scn.sigma_prr_m_s**2)])

    def hx(x, sp, sv):
        d = sp - x[0:3]
        rho = np.sqrt((d * d).sum(axis=1))
        u = d / rho[:, None]
        return np.concatenate([rho + x[3], (u * (sv - x[4:7])).sum(axis=1) + x[7]])

    def Hj(x, sp, sv):
        d = sp - x[0:3]
        rho = np.sqrt((d * d).sum(axis=1))
        u = d / rho[:, None]
        w = sv - x[4:7]
        H = np.zeros((8, 11))
        H[:4, 0:3] = -u
        H[:4, 3] = 1.0
        uw = (u * w).sum(axis=1)
        H[4:, 0:3] = -(w - uw[:, None] * u) / rho[:, None]
        H[4:, 4:7] = -u
        H[4:, 7] = 1.0
        return H

    if kind == "ekf":
        f = ExtendedKalmanFilter(dim_x=11, dim_z=8)
        f.F, f.Q, f.R = F, Q, R
    else:
        pts = MerweScaledSigmaPoints(11, alpha=1.0, beta=0.0, kappa=3.0 - 11)
        f = UnscentedKalmanFilter(dim_x=11, dim_z=8, dt=scn.dt_s, hx=hx, fx=lambda x, dt: F @ x, points=pts)
        f.Q, f.R = Q, R
    f.x = x0.copy()
    f.P = P0.copy()
    n_steps = min(n_steps, zs.shape[0])
    t0 = time.perf_counter()
    for k in range(n_steps):
        sp, sv = sps[k, 0], svs[k, 0]
        f.predict()
        if kind == "ekf":
            f.update(zs[k, 0], Hj, hx, args=(sp, sv), hx_args=(sp, sv))
        else:
            f.update(zs[k, 0], sp=sp, sv=sv)
    return (time.perf_counter() - t0) / n_steps


def run(trials=(1, 100, 10_000), steps=None, backends=("numba", "numpy"), rounds=5, progress=None):
    """Per trial-step times, the minimum over `rounds` interleaved rounds of each side.

    The machine's speed drifts (shared cores, frequency changes), so FilterPy and
    skyfuse are timed alternately, round after round, and each side keeps its best
    round: the ratio then compares the two under the same conditions.
    """
    max_n = max(trials)
    data = _scenario_data(max_n, 1 + max(steps or 0, 40))
    rows = []
    for kind in ("ekf", "ukf"):
        for n in trials:
            # enough steps for a stable figure on small batches, few on big ones
            ns = steps or int(min(40, max(20, 4e4 // (n * (5 if kind == "ukf" else 1)))))
            sub = data[:4] + (data[4][:ns + 1], data[5][:ns + 1], data[6][:ns + 1])
            fp, sk = [], {be: [] for be in backends}
            for _ in range(rounds):
                fp.append(_time_filterpy(kind, *data, n_steps=40 if kind == "ekf" else 20))
                for be in backends:
                    sk[be].append(_time_skyfuse(kind, be, *sub, n_trials=n))
            row = {"filter": kind, "trials": n, "filterpy_s_per_trial_step": min(fp), "rounds": rounds}
            for be in backends:
                row[f"{be}_s_per_trial_step"] = min(sk[be])
            row["skyfuse_s_per_trial_step"] = row[f"{backends[0]}_s_per_trial_step"]
            row["speedup"] = row["filterpy_s_per_trial_step"] / row["skyfuse_s_per_trial_step"]
            rows.append(row)
            if progress:
                progress(f"{kind} N={n}: {row['speedup']:.1f}x FilterPy")
    return rows


def table(rows, backends) -> str:
    head = f"{'filter':<6} {'trials':>7} | {'FilterPy us':>11} | " + " | ".join(
        f"{b + ' us':>10} {'x FilterPy':>10}" for b in backends)
    out = [head, "-" * len(head)]
    for r in rows:
        cells = " | ".join(f"{r[f'{b}_s_per_trial_step'] * 1e6:>10.3f} {r['filterpy_s_per_trial_step'] / r[f'{b}_s_per_trial_step']:>10.1f}"
                           for b in backends)
        out.append(f"{r['filter']:<6} {r['trials']:>7} | {r['filterpy_s_per_trial_step'] * 1e6:>11.2f} | {cells}")
    out.append("times are per trial-step (predict + update, model evaluation included), best of "
               f"{rows[0]['rounds']} interleaved rounds per side; "
               f"numba threads: {kernels.numba_threads()}")
    return "\n".join(out)


@dataclass(frozen=True)
class FiltersBenchOptions:
    """`skyfuse bench filters`'s options, declared once (sitl.params)."""

    trials: list = param(default_factory=lambda: [1, 100, 10_000], check=several(integer(lo=1), "+"), doc="batch sizes to time")
    steps: int | None = param(None, check=optional(integer(lo=1)), doc="steps per timing",
                              default_help="default: enough for ~1 s per case")
    json: Path | None = param(None, check=optional(OUTPUT_FILE), metavar="FILE", doc="also write the table as JSON")
    backend: str = param("numba", check=choice("numba", "numpy"), doc="skyfuse kernels to time")

    __post_init__ = validate


def add_args(p) -> None:
    add_flags(p, FiltersBenchOptions)


def main(args) -> int:
    try:
        import filterpy  # noqa: F401
    except ImportError:
        from sitl.app.args import UsageError

        raise UsageError("bench filters needs FilterPy as its peer: pip install 'skyfuse[bench]'") from None
    backends = (args.backend, "numpy") if args.backend == "numba" else ("numpy",)
    if not kernels.HAVE_NUMBA:
        backends = ("numpy",)
    rows = run(tuple(args.trials), args.steps, backends,
               progress=progress_printer(False, "bench filters"))
    print(table(rows, backends))
    if args.json:
        write_json(args.json, {"rows": rows}, scenario=options_scenario(args))
        print(f"wrote {args.json}")
    return 0
