"""The run report's own figures: a map of the tracks (no tiles: matplotlib in local east/north
frames, metres, with a scale bar) and the estimates' errors against time, both from the
tracks of the run's bus log."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from sitl.app.report.tracks import Tracks, errors_at_common_epochs

MAP_FIGURE = "map.png"
ERRORS_FIGURE = "run_errors.png"
ELLIPSE_P = 0.95  # confidence of the uncertainty ellipses drawn
UAV_COLORS = ("C0", "C1", "C4", "C5", "C6", "C8", "C9")


def _ref(lat_deg: float, lon_deg: float, h_m: float):
    return math.radians(lat_deg), math.radians(lon_deg), float(h_m)


def radar_site(sonde: dict):
    """(lat deg, lon deg, h m) of the radar and ground receiver: gcpp_offset_m from the launch
    pad at gcpp_bearing_deg (the scenario's [sonde] section, as the vehicles place it)."""
    from sitl.geodesy import ecef_to_geodetic, enu_to_ecef

    lat0, lon0, h0 = _ref(*sonde["launch"])
    b = math.radians(float(sonde["gcpp_bearing_deg"]))
    off = float(sonde["gcpp_offset_m"])
    lat, lon, h = ecef_to_geodetic(enu_to_ecef(np.array([off * math.sin(b), off * math.cos(b), 0.0]), lat0, lon0, h0))
    return math.degrees(float(lat)), math.degrees(float(lon)), float(h)


def _enu(pos_ecef_m, ref):
    from sitl.geodesy import ecef_to_enu

    return ecef_to_enu(np.asarray(pos_ecef_m, float), *ref)


def horizontal_cov_m2(cov_ecef_m2, ref) -> np.ndarray:
    """The (east, north) marginal of an ECEF position covariance (..., 3, 3) at ``ref``: the 2-D
    projection of the 3-D uncertainty onto the local horizontal plane."""
    from sitl.geodesy import enu_rotation

    r = enu_rotation(ref[0], ref[1])
    p = r @ np.asarray(cov_ecef_m2, float) @ r.T
    return p[..., 0:2, 0:2]


def ellipse_axes(cov2_m2, p: float = ELLIPSE_P):
    """(semi-major m, semi-minor m, angle deg of the major axis from east, counter-clockwise) of
    the probability-p ellipse of a 2-D Gaussian: the eigenvectors of the covariance, scaled by
    sqrt(chi2_2^-1(p)) = sqrt(-2 ln(1 - p))."""
    k = math.sqrt(-2.0 * math.log(1.0 - p))
    w, v = np.linalg.eigh(np.asarray(cov2_m2, float))
    w = np.clip(w, 0.0, None)
    return k * math.sqrt(w[1]), k * math.sqrt(w[0]), math.degrees(math.atan2(v[1, 1], v[0, 1]))


def _draw_ellipse(ax, centre, cov2, color, label=None):
    from matplotlib.patches import Ellipse

    a, b, ang = ellipse_axes(cov2)
    ax.add_patch(Ellipse(centre, 2 * a, 2 * b, angle=ang, fill=False, color=color, lw=1.4, label=label))
    return a


def _scale(ax, span_m: float) -> None:
    from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

    target = span_m / 5.0
    mag = 10 ** math.floor(math.log10(max(target, 1e-3)))
    length = next(m * mag for m in (5, 2, 1) if m * mag <= target) if target >= mag else mag
    text = f"{length / 1000:g} km" if length >= 1000 else f"{length:g} m"
    ax.add_artist(AnchoredSizeBar(ax.transData, length, text, "lower right", pad=0.5, sep=4, frameon=True,
                                  size_vertical=span_m / 250.0))


def _set_extent(ax, pts: np.ndarray, min_half_m: float = 200.0) -> float:
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    c = 0.5 * (lo + hi)
    half = max(0.55 * float(np.max(hi - lo)), min_half_m)
    ax.set_xlim(c[0] - half, c[0] + half)
    ax.set_ylim(c[1] - half, c[1] + half)
    ax.set_aspect("equal")
    return 2 * half


def _inset(ax, centre, truth_pt, track_en, cov2, color) -> None:
    """A zoom about the last estimate (in metres from it): its ellipse is metres across on a map
    kilometres wide."""
    a, _, _ = ellipse_axes(cov2)
    c = np.asarray(centre, float)
    d = np.asarray(truth_pt, float) - c
    half = max(1.5 * a, 1.3 * float(np.hypot(*d)), 5.0)
    ins = ax.inset_axes([0.13, 0.63, 0.3, 0.3])
    rel = track_en - c
    ins.plot(rel[:, 0], rel[:, 1], color=color, lw=0.8)
    _draw_ellipse(ins, (0.0, 0.0), cov2, color)
    ins.plot(0.0, 0.0, "o", color=color, ms=4)
    ins.plot(*d, "k*", ms=9)
    ins.set_xlim(-half, half)
    ins.set_ylim(-half, half)
    ins.set_aspect("equal")
    ins.tick_params(labelsize=6)
    ins.set_xlabel("m from the last estimate", fontsize=6, labelpad=1)
    ins.set_title("zoom: last epoch (star: truth)", fontsize=7)
    ins.grid(alpha=0.3)


def plot_map(tracks: Tracks, scenario: dict, out: Path, title: str) -> Path | None:
    """The map (one panel per area: the beacon's, with the UAVs; the sonde's, about the radar
    site). None when the log holds no track."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sitl.app.experiments.common import save_figure

    panels = []
    beacon = [k for k in tracks.truth if k[0] == "beacon"] + [k for k in tracks.estimate if k[0] == "beacon"]
    uavs = sorted((k for k in tracks.truth if k[0] == "uav"), key=lambda k: (len(k[1]), k[1]))
    if beacon or uavs:
        panels.append("beacon")
    sonde_keys = [k for k in tracks.truth if k[0] == "sonde"] + [k for k in tracks.estimate if k[0] == "sonde"]
    if sonde_keys and scenario.get("sonde"):
        panels.append("sonde")
    if not panels:
        return None
    fig, axes = plt.subplots(1, len(panels), figsize=(7.2 * len(panels), 7.2), squeeze=False, constrained_layout=True)
    conf = f"{100 * ELLIPSE_P:g} %"
    for ax, panel in zip(axes[0], panels):
        pts = []
        if panel == "beacon":
            start = scenario["beacon"]["start"]
            ref = _ref(*start)
            origin = f"the beacon's start ({start[0]:.4f} N, {start[1]:.4f} E)"
            for i, key in enumerate(uavs):
                en = _enu(tracks.truth[key].pos_ecef_m, ref)
                ax.plot(en[:, 0], en[:, 1], color=UAV_COLORS[i % len(UAV_COLORS)], lw=0.9, label=f"UAV {key[1]} (truth)")
                ax.plot(*en[-1, 0:2], ">", color=UAV_COLORS[i % len(UAV_COLORS)], ms=5)
                pts.append(en[:, 0:2])
            kinds = "beacon"
        else:
            site = radar_site(scenario["sonde"])
            ref = _ref(*site)
            origin = f"the radar site ({site[0]:.4f} N, {site[1]:.4f} E)"
            ax.plot(0.0, 0.0, "k^", ms=10, label=f"radar {scenario['sonde'].get('radar_id', '')} and ground receiver")
            launch = _enu(_geodetic_ecef(scenario["sonde"]["launch"]), ref)
            ax.plot(launch[0], launch[1], "kx", ms=8, label="launch pad")
            pts.append(np.array([[0.0, 0.0], launch[0:2]]))
            kinds = "sonde"
        for key, tr in tracks.truth.items():
            if key[0] != kinds:
                continue
            en = _enu(tr.pos_ecef_m, ref)
            ax.plot(en[:, 0], en[:, 1], "k-", lw=1.6, label=f"{kinds} {key[1]}: truth")
            ax.plot(*en[-1, 0:2], "k*", ms=10)
            pts.append(en[:, 0:2])
        for key, tr in tracks.estimate.items():
            if key[0] != kinds:
                continue
            en = _enu(tr.pos_ecef_m, ref)
            ax.plot(en[:, 0], en[:, 1], color="C3", lw=1.0, ls="--", label=f"{kinds} {key[1]}: estimate")
            cov2 = horizontal_cov_m2(tr.cov_pos_m2[-1], ref)
            a, b, _ = ellipse_axes(cov2)
            _draw_ellipse(ax, en[-1, 0:2], cov2, "C3",
                          label=f"{conf} ellipse of the last estimate ({a:,.1f} x {b:,.1f} m semi-axes)")
            ax.plot(*en[-1, 0:2], "o", color="C3", ms=4)
            pts.append(en[:, 0:2])
            truth = tracks.truth.get(key)
            if truth is not None:
                _inset(ax, en[-1, 0:2], _enu(truth.pos_ecef_m[-1], ref)[0:2], en[:, 0:2], cov2, "C3")
        span = _set_extent(ax, np.concatenate(pts))
        _scale(ax, span)
        ax.set_xlabel(f"east of {origin}, m")
        ax.set_ylabel("north, m")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.08), ncol=2)
        ax.set_title(f"{kinds} area: tracks in a local east/north frame (markers: last epoch)", fontsize=9)
    fig.suptitle(f"{title}\nellipses: {conf} confidence, the horizontal (east, north) marginal of the estimate's "
                 "3-D position covariance", fontsize=10)
    return save_figure(fig, out / MAP_FIGURE)


def _geodetic_ecef(lla):
    from sitl.geodesy import geodetic_to_ecef

    return geodetic_to_ecef(math.radians(lla[0]), math.radians(lla[1]), float(lla[2]))


def nees_summary(tracks: Tracks) -> dict:
    """Per target: the mean position NEES (3 dof) of the estimates over the run's epochs, and
    the fraction of epochs inside the 99 % chi-square band of one epoch (one run: one draw per
    epoch; the epochs of a run are correlated, so the mean has no band of its own here)."""
    import scipy.stats

    lo, hi = (float(scipy.stats.chi2.ppf(q, 3)) for q in (0.005, 0.995))
    out = {}
    for key, est in tracks.estimate.items():
        truth = tracks.truth.get(key)
        if truth is None:
            continue
        _, e, cov = errors_at_common_epochs(truth, est)
        if not len(e):
            continue
        try:
            nees = np.einsum("ti,ti->t", e, np.linalg.solve(cov, e[..., None])[..., 0])
        except np.linalg.LinAlgError:
            continue
        out[f"{key[0]}/{key[1]}"] = {"mean_nees_pos": float(np.mean(nees)), "band_99_one_epoch": [lo, hi],
                                     "fraction_inside": float(np.mean((nees >= lo) & (nees <= hi))),
                                     "epochs": int(nees.size)}
    return out


def plot_errors(tracks: Tracks, out: Path, title: str, t0_gps_s: float | None) -> Path | None:
    """|estimate - truth| and the estimate's own 3-D 1-sigma (sqrt tr P_pos) per target against time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sitl.app.experiments.common import save_figure

    pairs = [(k, tracks.truth[k], e) for k, e in tracks.estimate.items() if k in tracks.truth]
    if not pairs:
        return None
    fig, axes = plt.subplots(len(pairs), 1, figsize=(10, 3.4 * len(pairs)), squeeze=False, constrained_layout=True)
    for ax, (key, tr, est) in zip(axes[:, 0], pairs):
        t, e, cov = errors_at_common_epochs(tr, est)
        ts = t - (t0_gps_s if t0_gps_s is not None else t[0])
        ax.plot(ts, np.linalg.norm(e, axis=1), color="C0", lw=1.0, label="|estimate - truth| (3-D)")
        ax.plot(ts, np.sqrt(np.trace(cov, axis1=1, axis2=2)), color="C3", lw=0.9, ls="--",
                label="the estimate's own 1-sigma, sqrt(tr P_pos)")
        ax.set_yscale("log")
        ax.set_ylabel("3-D position error, m\n(log scale)")
        ax.set_title(f"{key[0]} {key[1]}: {len(t)} estimates scored against the truth", fontsize=9)
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8, loc="upper right")
    axes[-1, 0].set_xlabel("time since the run's start, s")
    fig.suptitle(title, fontsize=10)
    return save_figure(fig, out / ERRORS_FIGURE)
