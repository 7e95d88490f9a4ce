"""Seed 001: EKF against UKF for receiver secondary processing, by Monte Carlo.

The scenario of the seed's table: an aircraft (initial speed 100 m/s, acceleration
5 m/s^2) tracked by a receiver from 4 satellites, pseudorange and pseudorange-rate per
channel, T = 0.01 s, 600 update steps; Singer manoeuvre model (alpha = 0.2 1/s) and a
clock whose frequency drift is a first-order Gauss-Markov process (mu = 0.1 1/s,
sigma 3 m/s). Both filters run on the SAME simulated trials; the posterior Cramer-Rao
bound (Tichavsky recursion) is computed for the same model along the same true
trajectories.

How the seed's description is read (the seed 001 paper, README "The papers"):
* The truth obeys the filters' own model (Singer + clock) with the initial state drawn
  from the filters' prior: its mean is the seed's deterministic start (100 m/s east,
  5 m/s^2 along the track), so the trajectory is "a second-order polynomial plus a
  correlated Gaussian part". With a matched model the PCRB is a true bound and NEES must
  be chi-square consistent.
* The seed's table gives the pseudorange error as "mean square ... , m: 100", the
  pseudo-velocity error as "mean square ..., m/s: 15" and the clock drift as "mean square
  ..., m/s: 3". The project's model notes read the first two as variances (sigma 10 m and sqrt(15) m/s).
  The units printed in the table (m and m/s, not m^2) and the seed's figure (the error
  standard deviation starting near 50 m after the first update) fit the other reading:
  "mean square deviation", i.e. the standard deviations sigma_D = 100 m and
  sigma_V = 15 m/s, like sigma_V' = 3 m/s. That is the default here
  (``noise_reading="sigma"``); ``noise_reading="variance"`` runs that reading; both are
  compared against the figure in the project's notes.
* The satellites are four GPS satellites of the built-in almanac, chosen for the least
  GDOP above the mask at the start; their light-time geometry (with Earth rotation) makes
  the measurements. The filters get the satellite states from the ephemeris at the
  transit time measured by their own pseudorange: no truth reaches them.

Memory stays flat: trials are stepped together and only per-step statistics are kept.
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from filters import metrics, models
from filters.ekf import ekf_step
from filters.ukf import SigmaPoints, ukf_predict, ukf_update
from sitl import geodesy
from sitl.constants import C_M_S
from sitl.gnss import orbits, ranging
from sitl.app.args import OUTPUT_DIR
from sitl.app.experiments.common import progress_printer, write_result
from sitl.params import (
    add_flags, backend_option, choice, default_of, integer, number, optional, param, quiet_option, require, validate,
)

N_STATE = 11
POS = [0, 1, 2]
_POSITIVE = number(0, lo_open=True)


@dataclass(frozen=True)
class EkfVsUkfScenario:
    """Parameters of the seed 001 simulation table (defaults are the seed's)."""

    steps: int = param(600, check=integer(lo=1), doc="update steps per trial")
    dt_s: float = param(0.01, check=_POSITIVE, doc="update interval, s")
    n_sats: int = param(4, check=integer(lo=4, what="an integer >= 4 (n_sats must be >= 4: position and clock "
                                                    "need 4 satellites)"),
                        doc="satellites the receiver tracks (the highest above the mask at the start)")
    sigma_pr_m: float = param(100.0, check=_POSITIVE,
                              doc="pseudorange noise (1 sigma), m; the table's \"mean square ..., m: 100\" read as a "
                                  "deviation")
    sigma_prr_m_s: float = param(15.0, check=_POSITIVE,
                                 doc="pseudo-velocity (pseudorange rate) noise (1 sigma), m/s; the table's \"mean "
                                     "square ..., m/s: 15\" read as a deviation")
    sigma_clock_drift_m_s: float = param(3.0, check=_POSITIVE, doc="receiver clock drift std (in range rate), m/s")
    alpha_1_s: float = param(0.2, check=_POSITIVE, doc="Singer manoeuvre (acceleration decorrelation) rate, 1/s")
    mu_1_s: float = param(0.1, check=_POSITIVE, doc="receiver clock drift decorrelation rate, 1/s")
    speed0_m_s: float = param(100.0, check=number(), doc="the receiver's initial speed (eastward), m/s")
    accel0_m_s2: float = param(5.0, check=number(), doc="the receiver's initial acceleration (eastward), m/s^2")
    sigma_a_m_s2: float = param(1.0, check=_POSITIVE, doc="Singer manoeuvre sigma, m/s^2 (not in the seed's table)")
    lat_deg: float = param(53.9, check=number(-90.0, what="a latitude in [-90, 90] deg"),
                           doc="the receiver's initial latitude, degrees")
    lon_deg: float = param(27.57, check=number(), doc="the receiver's initial longitude, degrees")
    h_m: float = param(3000.0, check=number(), doc="the receiver's initial height above the ellipsoid, m")
    t0_gps_s: float = param(orbits.DEFAULT_TOA_GPS_S + 3600.0, check=number(),
                            doc="GPS time of the first epoch, s (an hour after the almanac's time of applicability)")
    el_mask_deg: float = param(10.0, check=number(), doc="elevation mask of the satellites chosen, degrees")
    # the prior (initial estimate) standard deviations, per axis
    sigma0_pos_m: float = param(100.0, check=_POSITIVE, doc="prior position std per axis, m")
    sigma0_clock_bias_m: float = param(100.0, check=_POSITIVE, doc="prior clock bias std (in range), m")
    sigma0_vel_m_s: float = param(10.0, check=_POSITIVE, doc="prior velocity std per axis, m/s")

    NOISE_READINGS = {"sigma": (100.0, 15.0), "variance": (10.0, math.sqrt(15.0))}

    @classmethod
    def with_noise_reading(cls, reading: str, **kw) -> "EkfVsUkfScenario":
        """The scenario with the table's noise figures read as deviations or as variances."""
        try:
            pr, prr = cls.NOISE_READINGS[reading]
        except KeyError:
            raise ValueError(f"noise reading must be one of {sorted(cls.NOISE_READINGS)}, got {reading!r}") from None
        return cls(**{"sigma_pr_m": pr, "sigma_prr_m_s": prr, **kw})

    def __post_init__(self):
        validate(self)
        require(self.lat_deg <= 90.0, "lat_deg", f"expected a latitude in [-90, 90] deg, got {self.lat_deg!r}")

    # ------------------------------------------------------------------ the model
    def transition(self):
        return models.singer_clock_transition(alpha_1_s=self.alpha_1_s, sigma_a_m_s2=self.sigma_a_m_s2,
                                         mu_1_s=self.mu_1_s, sigma_clock_drift_m_s=self.sigma_clock_drift_m_s)

    def prior(self):
        """Prior mean (11,) and covariance (11, 11) in the seed's state order."""
        lat, lon = math.radians(self.lat_deg), math.radians(self.lon_deg)
        pos = geodesy.geodetic_to_ecef(lat, lon, self.h_m)
        R_enu = geodesy.enu_rotation(lat, lon)  # enu = R @ ecef
        east = R_enu[0]
        x0 = np.zeros(N_STATE)
        x0[0:3] = pos
        x0[4:7] = self.speed0_m_s * east
        x0[8:11] = self.accel0_m_s2 * east
        sd = np.empty(N_STATE)
        sd[0:3] = self.sigma0_pos_m
        sd[3] = self.sigma0_clock_bias_m
        sd[4:7] = self.sigma0_vel_m_s
        sd[7] = self.sigma_clock_drift_m_s  # the drift's stationary sigma
        sd[8:11] = self.sigma_a_m_s2  # Singer's stationary sigma
        return x0, np.diag(sd**2)


def choose_satellites(constellation, rx_pos_ecef_m, t_gps_s, n_sats, el_mask_rad):
    """Indices of the n_sats visible satellites with the least GDOP (exhaustive search)."""
    from itertools import combinations

    pos, _ = orbits.sat_state_ecef(constellation, t_gps_s)
    _, el, _ = geodesy.ecef_to_aer(rx_pos_ecef_m, pos)
    vis = np.flatnonzero(el >= el_mask_rad)
    if vis.size < n_sats:
        raise ValueError(f"only {vis.size} satellites above the mask at the start; {n_sats} needed")
    los = pos[vis] - rx_pos_ecef_m
    los /= np.linalg.norm(los, axis=-1, keepdims=True)
    best, best_gdop = None, np.inf
    for combo in combinations(range(vis.size), n_sats):
        G = np.hstack([-los[list(combo)], np.ones((n_sats, 1))])
        try:
            gdop = math.sqrt(np.trace(np.linalg.inv(G.T @ G)))
        except np.linalg.LinAlgError:
            continue
        if gdop < best_gdop:
            best, best_gdop = combo, gdop
    return vis[list(best)], best_gdop


def _sqrtm_psd(Q):
    """A square root L (L L' = Q) of a positive semidefinite matrix."""
    w, V = np.linalg.eigh(0.5 * (Q + Q.T))
    return V * np.sqrt(np.clip(w, 0.0, None))


@dataclass
class _Stats:
    """Per-step accumulators of one filter's errors over the trials."""

    steps: int
    err_mean: list = field(default_factory=list)
    err_std: list = field(default_factory=list)
    rmse: list = field(default_factory=list)
    nees: list = field(default_factory=list)  # mean NEES over trials per step
    nis: list = field(default_factory=list)
    diverged: int = 0

    def add(self, x_est, P_est, x_true, nis):
        e = x_est - x_true
        sph = np.linalg.norm(e[:, POS], axis=1)
        ok = np.isfinite(sph)
        self.diverged = max(self.diverged, int((~ok).sum()))
        sph = sph[ok]
        self.err_mean.append(float(sph.mean()))
        self.err_std.append(float(sph.std(ddof=1)) if sph.size > 1 else 0.0)
        self.rmse.append(float(np.sqrt(np.mean(sph**2))))
        self.nees.append(float(np.mean(metrics.nees(e[ok], P_est[ok]))))
        self.nis.append(float(np.mean(nis[ok])))


@dataclass(frozen=True)
class Setup:
    """Everything fixed for a run: satellites, model, prior, noise."""

    scn: EkfVsUkfScenario
    const: object
    gdop: float
    transition: object
    x0: np.ndarray
    P0: np.ndarray
    sigmas: np.ndarray  # (m,) measurement standard deviations, pseudoranges first

    @classmethod
    def make(cls, scn: EkfVsUkfScenario) -> "Setup":
        const_all = orbits.gps_constellation()
        x0, P0 = scn.prior()
        sats, gdop = choose_satellites(const_all, x0[0:3], scn.t0_gps_s, scn.n_sats, math.radians(scn.el_mask_deg))
        sig = np.concatenate([np.full(scn.n_sats, scn.sigma_pr_m), np.full(scn.n_sats, scn.sigma_prr_m_s)])
        return cls(scn, const_all.subset(sats), gdop, scn.transition(), x0, P0, sig)

    def measurement_model(self, sat_pos, sat_vel):
        return models.PseudorangeDoppler(sat_pos, sat_vel, self.scn.sigma_pr_m, self.scn.sigma_prr_m_s)

    def stream(self, trials: int, rng: np.random.Generator):
        """The world: yields (k, t_rx, x_true, z, filter_meas_model, geometry) for k = 1..steps.

        x_true (trials, 11) follows the seed's model from a draw of the prior; z (trials, m)
        are pseudoranges and rates from the light-time geometry plus white noise. The
        filter's measurement model carries the satellite states that a receiver computes
        from the ephemeris at its own measured transit time z/c (no truth in it).
        """
        scn = self.scn
        F = self.transition.F(None, scn.dt_s)
        LQ = _sqrtm_psd(self.transition.Q(scn.dt_s))  # the seed's clock Q is singular: no Cholesky
        x_true = self.x0 + rng.standard_normal((trials, N_STATE)) @ np.linalg.cholesky(self.P0).T
        yield 0, scn.t0_gps_s, x_true, None, None, None
        for k in range(1, scn.steps + 1):
            t_rx = scn.t0_gps_s + k * scn.dt_s
            x_true = x_true @ F.T + rng.standard_normal((trials, N_STATE)) @ LQ.T
            geo = ranging.light_time_geometry(t_rx, x_true[:, 0:3], x_true[:, 4:7], self.const)
            z = np.concatenate([geo.range_m + x_true[:, 3:4], geo.range_rate_m_s + x_true[:, 7:8]], axis=1)
            z += rng.standard_normal(z.shape) * self.sigmas
            sat_pos, sat_vel = ranging.sat_state_at_reception_frame(t_rx, z[:, :scn.n_sats] / C_M_S, self.const)
            yield k, t_rx, x_true, z, self.measurement_model(sat_pos, sat_vel), geo


def run(scn: EkfVsUkfScenario, trials: int, seed: int, backend=None, progress=None):
    """Run the experiment; returns the result dictionary (the content of result.json)."""
    t_wall = time.perf_counter()
    rng = np.random.default_rng(seed)
    setup = Setup.make(scn)
    x0, P0, trans = setup.x0, setup.P0, setup.transition
    m = 2 * scn.n_sats
    points = SigmaPoints.julier(N_STATE)
    stream = setup.stream(trials, rng)
    _, _, x_true, _, _, _ = next(stream)

    xe = np.broadcast_to(x0, (trials, N_STATE)).copy()
    Pe = np.broadcast_to(P0, (trials, N_STATE, N_STATE)).copy()
    xu, Pu = xe.copy(), Pe.copy()
    ekf, ukf = _Stats(scn.steps), _Stats(scn.steps)
    prior_err = np.linalg.norm((xe - x_true)[:, POS], axis=1)

    # PCRB (Tichavsky et al. 1998), advanced one epoch at a time along the trials:
    # J_k = (Q + F J_{k-1}^-1 F')^-1 + E[H_k' R^-1 H_k], expectation over the true states.
    B = P0.copy()
    R = np.diag(setup.sigmas**2)
    pcrb_pos = []
    t_filter = {"ekf": 0.0, "ukf": 0.0}
    report_every = max(1, scn.steps // 10)
    for k, t_rx, x_true, z, meas, geo in stream:
        t = time.perf_counter()
        res = ekf_step(xe, Pe, z, trans, meas, scn.dt_s, backend=backend)
        xe, Pe = res.x, res.P
        t_filter["ekf"] += time.perf_counter() - t
        ekf.add(xe, Pe, x_true, res.nis)

        t = time.perf_counter()
        xp, Pp = ukf_predict(xu, Pu, trans, scn.dt_s, points=points, backend=backend)
        res = ukf_update(xp, Pp, z, meas, points=points, backend=backend)
        xu, Pu = res.x, res.P
        t_filter["ukf"] += time.perf_counter() - t
        ukf.add(xu, Pu, x_true, res.nis)

        # PCRB: the same measurement model evaluated at the true states (scoring side)
        true_meas = setup.measurement_model(geo.sat_pos_ecef_m, geo.sat_vel_ecef_m_s)
        B = metrics.pcrb(np.linalg.inv(B), trans, scn.dt_s, 1, H=true_meas.h_and_H(x_true)[1][None], R=R)[0]
        pcrb_pos.append(float(np.sqrt(np.trace(B[np.ix_(POS, POS)]))))

        if progress and (k % report_every == 0 or k == scn.steps):
            progress(f"rmse ekf {ekf.rmse[-1]:.2f} m  ukf {ukf.rmse[-1]:.2f} m  "
                     f"sqrt(PCRB) {pcrb_pos[-1]:.2f} m  ({time.perf_counter() - t_wall:.1f} s)", done=k, total=scn.steps)

    const, gdop = setup.const, setup.gdop

    last = slice(max(0, scn.steps - 100), scn.steps)
    result = {
        "experiment": "ekf-vs-ukf",
        "schema": None,  # set when written (sitl.app.provenance.SCHEMA)
        "seed_paper": "001",
        "trials": trials,
        "steps": scn.steps,
        "measurements_per_step": m,
        "state_dim": N_STATE,
        "seed": seed,
        "wall_s": None,
        "filter_wall_s": t_filter,
        "satellites": [str(s) for s in const.sat_id],
        "gdop_at_start": gdop,
        "scenario": asdict(scn),
        "prior_spherical_error_mean_m": float(prior_err.mean()),
        "prior_spherical_error_std_m": float(prior_err.std(ddof=1)) if trials > 1 else 0.0,
        "pcrb_position_m": pcrb_pos,
    }
    # Bounds for the NEES averaged over the (independent) trials at one step; the average
    # over the last 100 steps as well is reported against the same band, since those
    # steps are strongly correlated and add few independent samples.
    lo, hi = metrics.chi2_bounds(N_STATE, trials, p=0.99)
    for name, st in (("ekf", ekf), ("ukf", ukf)):
        anees = float(np.mean(st.nees[last])) / N_STATE
        result[name] = {
            "spherical_error_mean_m": st.err_mean,
            "spherical_error_std_m": st.err_std,
            "rmse_position_m": st.rmse,
            "mean_nees": st.nees,
            "mean_nis": st.nis,
            "anees": anees,
            "anees_bounds_99": [lo / N_STATE, hi / N_STATE],
            "diverged_trials": st.diverged,
            "rmse_over_sqrt_pcrb_last100": float(np.mean(np.array(st.rmse[last]) / np.array(pcrb_pos[last]))),
        }
    # how far apart the two filters are, per step, relative to the EKF's RMSE
    d = np.abs(np.asarray(ekf.rmse) - np.asarray(ukf.rmse)) / np.asarray(ekf.rmse)
    result["ekf_ukf_rmse_max_rel_diff"] = float(d.max())
    result["wall_s"] = time.perf_counter() - t_wall
    return result


def summary_table(res: dict) -> str:
    """The table printed by `skyfuse demo` and the experiment."""
    steps = res["steps"]
    rows = [f"seed 001: EKF vs UKF, {res['trials']} trials x {steps} steps, "
            f"{res['measurements_per_step']} measurements/step, satellites {' '.join(res['satellites'])} "
            f"(GDOP {res['gdop_at_start']:.2f})"]
    marks = sorted({1, 10, 50, 100, 200, 300, 400, 500, steps} & set(range(1, steps + 1)))
    rows.append(f"{'step':>6} | {'EKF mean':>9} {'EKF std':>8} {'EKF rmse':>9} | {'UKF mean':>9} {'UKF std':>8} "
                f"{'UKF rmse':>9} | {'sqrt PCRB':>9}")
    for k in marks:
        e, u = res["ekf"], res["ukf"]
        i = k - 1
        rows.append(f"{k:>6} | {e['spherical_error_mean_m'][i]:>9.2f} {e['spherical_error_std_m'][i]:>8.2f} "
                    f"{e['rmse_position_m'][i]:>9.2f} | {u['spherical_error_mean_m'][i]:>9.2f} "
                    f"{u['spherical_error_std_m'][i]:>8.2f} {u['rmse_position_m'][i]:>9.2f} | "
                    f"{res['pcrb_position_m'][i]:>9.2f}")
    lo, hi = res["ekf"]["anees_bounds_99"]
    rows.append(f"ANEES over the last 100 steps: EKF {res['ekf']['anees']:.3f}  UKF {res['ukf']['anees']:.3f} "
                f"(99 % chi-square band of one step's mean over {res['trials']} trials: {lo:.3f}..{hi:.3f})")
    rows.append(f"largest |RMSE_EKF - RMSE_UKF| / RMSE_EKF over all steps: {res['ekf_ukf_rmse_max_rel_diff']:.2e}")
    rows.append(f"RMSE / sqrt(PCRB) over the last 100 steps: EKF {res['ekf']['rmse_over_sqrt_pcrb_last100']:.3f}  "
                f"UKF {res['ukf']['rmse_over_sqrt_pcrb_last100']:.3f}")
    rows.append(f"wall {res['wall_s']:.1f} s (filters: EKF {res['filter_wall_s']['ekf']:.1f} s, "
                f"UKF {res['filter_wall_s']['ukf']:.1f} s)")
    return "\n".join(rows)


def _save(fig, path: Path) -> Path:
    import matplotlib.pyplot as plt

    fig.tight_layout()
    fig.savefig(path, dpi=110, bbox_inches="tight", pad_inches=0.1)
    plt.close(fig)
    return path


def plot(res: dict, out: Path) -> list[Path]:
    """PNG figures like the seed's: std (and mean) of the spherical error per step."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sitl.app.experiments.common import run_label

    k = np.arange(1, res["steps"] + 1)
    pc = np.asarray(res["pcrb_position_m"])
    N = res["trials"]
    head = run_label("ekf-vs-ukf", paper="001", seed=res.get("seed"), trials=N)
    files = []
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.8))
    ax = axes[0]
    ax.plot(k, res["ekf"]["spherical_error_std_m"], label="EKF: std over trials", lw=2)
    ax.plot(k, res["ukf"]["spherical_error_std_m"], "--", label="UKF: std over trials", lw=2)
    ax.set_xlabel("update step k")
    ax.set_ylabel("std of the spherical error |X^ - X|, m")
    ax.set_title(f"the paper's figure: std of |X^ - X| over {N} trials", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend()
    ax = axes[1]
    ax.plot(k, res["ekf"]["rmse_position_m"], label="EKF: position RMSE over trials", lw=2)
    ax.plot(k, res["ukf"]["rmse_position_m"], "--", label="UKF: position RMSE over trials", lw=2)
    ax.plot(k, res["ekf"]["spherical_error_mean_m"], ":", label="EKF: mean spherical error", lw=1.5)
    ax.plot(k, pc, "k-", label="sqrt(tr PCRB_pos)", lw=1)
    ax.set_yscale("log")
    ax.set_xlabel("update step k")
    ax.set_ylabel("position error, m (log scale)")
    ax.set_title("RMSE and mean against the posterior Cramer-Rao bound", fontsize=10)
    ax.grid(alpha=0.3, which="both")
    ax.legend()
    fig.suptitle(head)
    files.append(_save(fig, out / "spherical_error.png"))

    fig, ax = plt.subplots(figsize=(7.5, 4.6))
    n = res["state_dim"]
    ax.plot(k, np.asarray(res["ekf"]["mean_nees"]) / n, label=f"EKF (ANEES of the last 100 steps {res['ekf']['anees']:.3f})")
    ax.plot(k, np.asarray(res["ukf"]["mean_nees"]) / n, "--",
            label=f"UKF (ANEES of the last 100 steps {res['ukf']['anees']:.3f})")
    lo, hi = res["ekf"]["anees_bounds_99"]
    ax.axhline(1.0, color="k", lw=0.8, label="expected value (1)")
    # the band is that of ONE step's mean over the N trials (chi2(n N) / (n N)); the 100 steps of
    # a trial are correlated, so their average has no band of 100 N independent draws
    ax.axhspan(lo, hi, color="0.85", zorder=0,
               label=f"99 % chi-square band of one step's mean over {N} trials ({lo:.3f}-{hi:.3f})")
    ax.set_xlabel("update step k")
    ax.set_ylabel(f"mean NEES over trials / n (n = {n} states), 1")
    ax.set_title(f"{head}\nconsistency: mean NEES per step", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    files.append(_save(fig, out / "nees.png"))
    return files


# ------------------------------------------------------------------ the command's options
@dataclass(frozen=True)
class EkfVsUkfOptions:
    """`skyfuse experiment ekf-vs-ukf`'s options, declared once (sitl.params): the flags, their
    --help texts, defaults and checks come from here."""

    trials: int = param(1000, check=integer(lo=1), doc="Monte Carlo trials")
    steps: int = param(default_of(EkfVsUkfScenario, "steps"), check=integer(lo=1), doc="update steps per trial",
                       note=", as in the seed")
    seed: int = param(1, check=integer(lo=0), doc="seed of the numpy Generator")
    out: Path = param(Path("out/ekf-vs-ukf"), check=OUTPUT_DIR, doc="output directory for result.json and PNG figures")
    noise_reading: str = param("sigma", check=choice(*EkfVsUkfScenario.NOISE_READINGS),
                               doc="read the seed table's 'mean square' noise figures (100 m, 15 m/s) as standard "
                                   "deviations (sigma) or as variances (variance: sigma 10 m, sqrt(15) m/s)")
    sigma_prr: float | None = param(None, check=optional(number(0, lo_open=True)), metavar="M_S",
                                    doc="override the pseudo-velocity noise sigma, m/s")
    sigma_a: float | None = param(None, check=optional(number(0, lo_open=True)), metavar="M_S2",
                                  doc="Singer manoeuvre sigma, m/s^2", note="; the seed gives none",
                                  shown=lambda: default_of(EkfVsUkfScenario, "sigma_a_m_s2"))
    backend: str = backend_option()
    quiet: bool = quiet_option()

    __post_init__ = validate


def add_args(p) -> None:
    add_flags(p, EkfVsUkfOptions)


def _scenario_from_args(args) -> EkfVsUkfScenario:
    kw = {"steps": getattr(args, "steps", default_of(EkfVsUkfOptions, "steps"))}
    if getattr(args, "sigma_prr", None) is not None:
        kw["sigma_prr_m_s"] = args.sigma_prr
    if getattr(args, "sigma_a", None) is not None:
        kw["sigma_a_m_s2"] = args.sigma_a
    return EkfVsUkfScenario.with_noise_reading(getattr(args, "noise_reading", default_of(EkfVsUkfOptions, "noise_reading")), **kw)


def write(res: dict, out: Path) -> list[Path]:
    out.mkdir(parents=True, exist_ok=True)
    from sitl.app.report import write_report

    figures = plot(res, out)
    res["figures"] = [Path(f).name for f in figures]  # as every experiment's result.json lists them
    write_result(out / "result.json", res, seed=res["seed"], scenario=res["scenario"])
    return [out / "result.json", *figures, write_report(out, figures=figures)]


def main(args) -> int:
    from sitl.app.args import UsageError

    try:
        scn = _scenario_from_args(args)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    backend = None if args.backend == "auto" else args.backend
    res = run(scn, args.trials, args.seed, backend=backend, progress=progress_printer(args.quiet, "ekf-vs-ukf"))
    files = write(res, args.out)
    print(summary_table(res))
    print("wrote " + ", ".join(str(f) for f in files))
    return 0
