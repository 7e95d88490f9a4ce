"""`skyfuse bench sonde`: a 2 h radiosonde flight at 1 Hz (seed 004), one sonde, against real time.

The case: the experiment's scenario (`sitl.app.experiments.sonde.SondeScenario`,
default 7200 s at 1 Hz, the relay's error budget, the radar loss and the GNSS outage), one
trial. The target is the fused tracker under 10 s. Cases, all measured in the same run,
rounds interleaved, each figure the minimum over rounds (the machine's speed drifts; the
minimum is the least disturbed run):

* ``fused, over the bus``: what `skyfuse experiment sonde` does for one trial with the fused
  tracker only: world, every message (truth, relay, radar) built, encoded, published and
  delivered by the in-memory bus, the tracker, its Estimates published and scored;
* ``fused, no bus``: the same world and the same messages (built, so schema-validated, as the
  tracker's API takes them) handed to the tracker directly (``on_message`` / ``step``); no
  encoding, no transport, no scorer. Its tracker share (``tracker_s``: ``on_message`` +
  ``step``, Estimates built) is reported beside it;
* ``world only``: the flight, the relay and the radar over the whole flight (no messages);
* ``three trackers, over the bus`` (unless ``--no-trio``): the experiment's trio (fused,
  radar-only, relay-only) on the same trial, for scale.

Ratios: ``x_real_time`` = simulated seconds / wall seconds; ``ratio_to_main`` = wall /
the main case's wall (main: fused, no bus).
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

from sitl.app.progress import progress_printer
from sitl.app.provenance import options_scenario, write_json
from sitl.app.args import OUTPUT_FILE
from sitl.params import add_flags, integer, number, optional, param, quiet_option, switch, validate

TARGET_S = 10.0


@dataclass(frozen=True)
class SondeBenchOptions:
    """`skyfuse bench sonde`'s options, declared once (sitl.params)."""

    duration: float = param(7200.0, check=number(0, lo_open=True), metavar="S", doc="simulated flight time, s at 1 Hz",
                            note=": the 2 h flight")
    rounds: int = param(2, check=integer(lo=1), doc="interleaved rounds; each figure is the minimum")
    seed: int = param(4, check=integer(lo=0), doc="random seed", note=", as the experiment")
    no_trio: bool = param(False, check=switch(), doc="skip the three-tracker case")
    json: Path | None = param(None, check=optional(OUTPUT_FILE), metavar="FILE", doc="also write the result as JSON")
    quiet: bool = quiet_option()

    __post_init__ = validate


def add_args(p) -> None:
    add_flags(p, SondeBenchOptions)


def _world_only(scn, seed: int, chunk: int = 300) -> float:
    from sitl.app.experiments.sonde import world

    w0 = time.perf_counter()
    _, _, _, _, track, radar, relay = world(scn, seed, [0])
    for c0 in range(0, scn.n_epochs, chunk):
        c1 = min(scn.n_epochs, c0 + chunk)
        relay.track(track.t_gps_s[c0:c1], track.pos_ecef_m[c0:c1], track.vel_ecef_m_s[c0:c1])
        radar.track(track.t_gps_s[c0:c1], track.pos_ecef_m[c0:c1], track.vel_ecef_m_s[c0:c1])
    return time.perf_counter() - w0


def _no_bus(scn, seed: int, chunk: int = 300) -> tuple[float, float, int]:
    """(wall, tracker share, estimates) of world + messages + the fused tracker, no bus."""
    from sitl.bus import RadarMeasurement, SondeRelay
    from sitl.app.experiments.sonde import RADAR_ID, RUN_ID, tracker_params, world

    from ground_station.sonde import SondeTracker
    w0 = time.perf_counter()
    _, _, _, _, track, radar, relay = world(scn, seed, [0])
    tr = SondeTracker(RUN_ID, tracker_params(scn, "fused"), radar_id=RADAR_ID)
    k_relay, k_radar = f"{RUN_ID}/sonde/s0000/relay", f"{RUN_ID}/radar/{RADAR_ID}/sonde/s0000"
    seq, n_est, t_tr = 0, 0, 0.0
    for c0 in range(0, scn.n_epochs, chunk):
        c1 = min(scn.n_epochs, c0 + chunk)
        rt = relay.track(track.t_gps_s[c0:c1], track.pos_ecef_m[c0:c1], track.vel_ecef_m_s[c0:c1])
        rm = radar.track(track.t_gps_s[c0:c1], track.pos_ecef_m[c0:c1], track.vel_ecef_m_s[c0:c1])
        for j in range(c1 - c0):
            t = float(rt.t_gps_s[j])
            d = rt.delivered[j, 0]
            msgs = [(k_relay, SondeRelay(
                t_gps_s=t, source_id="gcpp", seq=seq, sat_ids=rt.sat_id[d], pseudorange_m=rt.pseudorange_m[j, 0][d],
                pseudo_doppler_m_s=rt.pseudo_doppler_m_s[j, 0][d], var_pseudorange_m2=rt.var_pr_m2[j, 0][d],
                var_pseudo_doppler_m2_s2=rt.var_prr_m2_s2[j, 0][d], sat_pos_ecef_m=rt.sat_pos_ecef_m[j, 0][d],
                sat_vel_ecef_m_s=rt.sat_vel_ecef_m_s[j, 0][d], ground_pos_ecef_m=rt.ground_pos_ecef_m))]
            if rm.range_valid[j, 0]:
                msgs.append((k_radar, RadarMeasurement(
                    t_gps_s=t, source_id=RADAR_ID, seq=seq, slant_range_m=float(rm.slant_range_m[j, 0]),
                    az_rad=float(rm.az_rad[j, 0]), el_rad=float(rm.el_rad[j, 0]),
                    var_range_m2=float(rm.var_range_m2[j, 0]), var_az_rad2=float(rm.var_az_rad2[j, 0]),
                    var_el_rad2=float(rm.var_el_rad2[j, 0]), angles_valid=bool(rm.angles_valid[j, 0]),
                    radar_pos_ecef_m=rm.site_pos_ecef_m)))
            seq += 1
            a = time.perf_counter()
            for key, msg in msgs:
                tr.on_message(key, msg)
            n_est += len(tr.step(t))
            t_tr += time.perf_counter() - a
    return time.perf_counter() - w0, t_tr, n_est


def _over_bus(scn, seed: int, modes) -> tuple[float, dict]:
    from sitl.app.experiments.sonde import run_trials

    w0 = time.perf_counter()
    raw = run_trials(scn, seed, [0], modes=modes)
    return time.perf_counter() - w0, raw["timing_s"]


def run(duration_s: float = 7200.0, rounds: int = 2, seed: int = 4, trio: bool = True, progress=None) -> dict:
    from sitl.app.experiments.sonde import MODES, SondeScenario

    scn = SondeScenario(duration_s=duration_s, white_baseline=False)
    say = progress or (lambda msg, **kw: None)
    # warm-up: loads (or compiles, on a fresh install) the kernels outside the timing
    warm = SondeScenario(duration_s=min(duration_s, 60.0), white_baseline=False)
    _over_bus(warm, seed, MODES)
    _no_bus(warm, seed)
    cases = ["fused_no_bus", "fused_bus", "world"] + (["trio_bus"] if trio else [])
    best = dict.fromkeys(cases, float("inf"))
    extra: dict = {}
    for r in range(rounds):
        for c in cases:
            if c == "fused_no_bus":
                w, t_tr, n_est = _no_bus(scn, seed)
                if w < best[c]:
                    extra["tracker_s"], extra["estimates"] = t_tr, n_est
            elif c == "fused_bus":
                w, tm = _over_bus(scn, seed, ("fused",))
                if w < best[c]:
                    extra["bus_timing_s"] = tm
            elif c == "trio_bus":
                w, _ = _over_bus(scn, seed, MODES)
            else:
                w = _world_only(scn, seed)
            best[c] = min(best[c], w)
            say(f"round {r + 1}/{rounds} {c}: {w:.2f} s")
    names = {"fused_no_bus": "fused, no bus (world + messages + tracker)",
             "fused_bus": "fused, over the bus",
             "world": "world only (flight, relay, radar)",
             "trio_bus": "fused + radar-only + relay-only, over the bus"}
    main = best["fused_no_bus"]
    rows = [{"case": names[c], "key": c, "wall_s": best[c], "x_real_time": duration_s / best[c],
             "ms_per_epoch": 1e3 * best[c] / scn.n_epochs, "ratio_to_main": best[c] / main} for c in cases]
    bt = extra.get("bus_timing_s", {})
    return {"bench": "sonde", "duration_s": duration_s, "dt_s": scn.dt_s, "epochs": scn.n_epochs, "trials": 1,
            "rounds": rounds, "seed": seed, "main": "fused_no_bus", "target_s": TARGET_S,
            "fused_tracker_s": extra.get("tracker_s"), "estimates": extra.get("estimates"),
            "fused_bus_split_s": {k: round(v, 3) for k, v in bt.items()},
            "meets_target_without_bus": bool(main < TARGET_S * duration_s / 7200.0),
            "meets_target_over_bus": bool(best["fused_bus"] < TARGET_S * duration_s / 7200.0), "rows": rows}


def table(res: dict) -> str:
    lines = [f"seed 004 sonde: {res['duration_s']:.0f} s at {1 / res['dt_s']:.0f} Hz, 1 sonde, min over "
             f"{res['rounds']} round(s)",
             f"{'case':<48} {'wall s':>8} {'x real time':>12} {'ms/epoch':>9} {'/ main':>7}"]
    for r in res["rows"]:
        lines.append(f"{r['case']:<48} {r['wall_s']:8.2f} {r['x_real_time']:12.1f} {r['ms_per_epoch']:9.3f} "
                     f"{r['ratio_to_main']:7.2f}")
    if res["fused_tracker_s"] is not None:
        lines.append(f"the fused tracker's share of 'fused, no bus' (on_message + step): {res['fused_tracker_s']:.2f} s")
    if res["fused_bus_split_s"]:
        lines.append("'fused, over the bus' split: " + ", ".join(f"{k} {v:.2f} s" for k, v in res["fused_bus_split_s"].items()))
    lines.append(f"target: the 2 h flight (fused tracker) in under {res['target_s']:g} s: without the bus "
                 f"{res['meets_target_without_bus']}, over the bus {res['meets_target_over_bus']}")
    return "\n".join(lines)


def main(args) -> int:
    res = run(args.duration, args.rounds, args.seed, trio=not args.no_trio,
              progress=progress_printer(args.quiet, "bench sonde"))
    print(table(res))
    if args.json:
        write_json(args.json, res, seed=args.seed, scenario=options_scenario(args))
        print(f"wrote {args.json}")
    return 0
