"""`skyfuse run SCENARIO.toml`, `skyfuse demo`, `skyfuse replay LOG`: the live SITL launcher.

run / demo:
  1. the scenario (TOML, validated; `demo`: the built-in default), with the command line's
     overrides (--speed, --duration, --seed, --zenoh, --gcs, --no-mavlink);
  2. an embedded Zenoh router (sitl.bus.router.Router), unless --zenoh names external ones;
  3. the launcher's own bus session: the bus log (every ``<run>/**`` payload, crash-safe,
     OUT/bus.log) and the errors of the ground station's estimates against the truth;
  4. the workers (sitl.app.supervisor): the vehicle groups and the ground station, each a
     ``python -m MODULE SPEC.json`` (OUT/specs/); once every one is ready, the common start
     time; a worker that dies is reported and restarted;
  5. a status line every wall second (stderr): simulated time, vehicles, messages per
     second, rejected inputs, the latest beacon and sonde errors;
  6. at the end of ``duration_s`` (simulated) everything stops by itself; Ctrl-C or SIGTERM
     stop it early; in both cases every worker is stopped (process groups, SIGTERM then
     SIGKILL) and every session and port closed. OUT/report.json and a printed summary.

Network faults (sitl.app.live_faults): with a [faults] table in the scenario the
launcher puts a fault proxy on every worker's Zenoh link and every vehicle's MAVLink link and
the workers filter their own publications; ``<run>/ctl/fault`` changes any of them while the
run goes (`skyfuse fault set`, which finds the router in OUT/run.json). report.json gets a
``faults`` block: per link the specs applied over time and the truth counters.

replay LOG: the ground station's inputs through the batch ground station (GroundStationNode on
the in-memory transport); prints the replayed estimates' errors against the recorded truth and
their difference from the estimates the live ground station published (recorded in the same
log), and which of two sources gave its decisions ("decisions:"):
  * "journal" (when OUT/gs_journal.log is beside the log; ground_station.journal): what each live
    ground-station incarnation consumed, in its order -- every input payload as it took it in,
    every advance() with its arguments -- through a node of the journal's own configuration and
    incarnation: the live estimates bit for bit, whatever the machine's load was;
  * "recorder clock" (no journal, or --no-journal): the log in the recorded order, on the
    recorded clock (each record's receive time: the launcher's simulation clock when the payload
    arrived, never the payload's own time), an epoch processed under the live rule (once every
    source publishing has delivered it, at the latest hold_wall_s x speed after it), the same
    time guard as live. The recorder is not the ground station: under load its arrival order
    and clock differ, and so, for some epochs, do the estimates.
A log with restarted workers replays like any other: their new incarnations are new streams
there too.

vehicles / ground_station are started by module name (sitl never imports them statically).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import shlex
import signal
import sys
import threading
from dataclasses import dataclass
from pathlib import Path

from sitl.app.args import UsageError, add_positional, options_of, repeatable
from sitl.app.hosts import Placements, placement_check
from sitl.params import add_flags, default_of, from_text, integer, number, optional, param, string, switch, validate
from sitl.pacing import Pacer, perf_now, wall_now

READY_TIMEOUT_S = 240.0  # first start compiles / loads the numba kernels
END_GRACE_WALL_S = 20.0  # after the last epoch: how long workers may take to finish


# ---------------------------------------------------------------------- arguments


# Each command's options are one frozen dataclass declared once (sitl.params.param: the check,
# the doc = the --help text, the default); add_flags gives the flags, options_of the instance.
# A flag left out means "the scenario's" (None); a default shown in --help that is the
# scenario's is read from its declaration (sitl.scenario), never written here.


def _scenario_gcs() -> str:
    return _scenario_mavlink("gcs")


def _scenario_mavlink(key: str):
    from sitl.scenario import MavlinkSection  # the help text's; imported when the flags are added
    return default_of(MavlinkSection, key)


#: ArduPilot SITL's instance stride: instance N's ports are the base ports + 10 N
INSTANCE_PORT_STRIDE = 10


def _shift_port(hostport: str, by: int) -> str:
    host, _, port = hostport.rpartition(":")
    return f"{host}:{int(port) + by}" if port.isdigit() and int(port) != 0 else hostport


def _out_option(default: str):
    """--out DIR of `demo` / `run` (the same flag, each command its default directory)."""
    return param(Path(default), check=from_text(Path), metavar="DIR", doc="report, bus log, tlogs, worker logs")


_SCENARIOS = "default: the scenario's"


@dataclass(frozen=True, kw_only=True)
class DemoOptions:
    """`skyfuse demo`'s options: the scenario's overrides (None: the scenario's) and the run's."""

    speed: float | None = param(None, check=optional(number(0, lo_open=True)), default_help=_SCENARIOS,
                                doc="x real time")
    duration: float | None = param(None, check=optional(number(0, lo_open=True)), metavar="S", default_help=_SCENARIOS,
                                   doc="simulated seconds, then everything stops")
    seed: int | None = param(None, check=optional(integer(lo=0)), default_help=_SCENARIOS, doc="random seed")
    out: Path = _out_option("out/demo")
    zenoh: list | None = param(None, check=repeatable(string()), metavar="tcp/HOST:PORT",
                               doc="connect to this Zenoh router instead of starting one (repeatable)")
    gcs: str | None = param(None, check=optional(string()), metavar="HOST:PORT", shown=_scenario_gcs,
                            doc="ground-control endpoint (taken as given: --instance does not shift it)")
    instance: int | None = param(None, check=optional(integer(lo=0, hi=5000)), metavar="N", default_help="default: 0",
                                 doc="ArduPilot SITL's -I N: every port of the run shifted by 10 N (the vehicles' "
                                     "UDP/TCP base port, the scenario's GCS port -- so every MAVLink block's --, the "
                                     "router's listen port unless 0), "
                                     "so that N runs side by side do not collide")
    base_port: int | None = param(None, check=optional(integer(lo=1024, hi=65000)), metavar="P",
                                  shown=lambda: _scenario_mavlink("base_port"),
                                  doc="vehicle i listens on P + 10 i (UDP, and TCP with [mavlink] tcp), before --instance; "
                                      "beyond 249 vehicles, MAVLink block k's system id s on P + (k - 1) + 10 (s - 1)")
    no_mavlink: bool = param(False, check=switch(), doc="no MAVLink endpoints")
    host: list | None = param(None, check=repeatable(placement_check()), metavar="WORKERS=COMMAND",
                              doc="start the workers whose names match WORKERS (vehicles*, gs) on another host through "
                                  "COMMAND, e.g. 'vehicles*=ssh -T hostB' (repeatable; sitl/app/hosts.py says what "
                                  "that host needs: give --zenoh an address it reaches)")
    batch: bool = param(False, check=switch(),
                        doc="batch mode: the same components in one process, simulated time, in-memory bus")
    quiet: bool = param(False, check=switch(), doc="no status line")

    __post_init__ = validate


@dataclass(frozen=True, kw_only=True)
class RunOptions(DemoOptions):
    """`skyfuse run SCENARIO`'s options: the scenario file, then `demo`'s."""

    out: Path = _out_option("out/run")
    scenario: Path = param(check=from_text(Path), cli=False, doc="scenario file (TOML)")  # positional


@dataclass(frozen=True, kw_only=True)
class ReplayOptions:
    """`skyfuse replay LOG`'s options."""

    log: Path = param(check=from_text(Path), cli=False,  # positional
                      doc="a bus log written by `skyfuse run` / `demo` (OUT/bus.log)")
    scenario: Path | None = param(None, check=optional(from_text(Path)), doc="the run's scenario",
                                  default_help="default: scenario.json beside the log, else the built-in default")
    json: Path | None = param(None, check=optional(from_text(Path)), metavar="FILE", doc="also write the result as JSON")
    no_journal: bool = param(False, check=switch(),
                             doc="re-derive the ground station's decisions on the recorder's clock even where its "
                                 "journal (gs_journal.log beside the log) would give them exactly")

    __post_init__ = validate


def add_run_args(p: argparse.ArgumentParser) -> None:
    add_positional(p, RunOptions, "scenario")
    add_flags(p, RunOptions)


def add_demo_args(p: argparse.ArgumentParser) -> None:
    add_flags(p, DemoOptions)


def add_replay_args(p: argparse.ArgumentParser) -> None:
    add_positional(p, ReplayOptions, "log")
    add_flags(p, ReplayOptions)


def _scenario_with_overrides(scn, args: DemoOptions):
    from sitl.scenario import ScenarioError, scenario_from_dict
    d = scn.to_dict()
    if args.speed is not None:
        d["run"]["speed"] = args.speed
    if args.duration is not None:
        d["run"]["duration_s"] = args.duration
    if args.seed is not None:
        d["run"]["seed"] = args.seed
    if args.zenoh:
        d["bus"]["zenoh"] = list(args.zenoh)
    if args.base_port is not None:
        d["mavlink"]["base_port"] = args.base_port
    shift = INSTANCE_PORT_STRIDE * (args.instance or 0)
    if shift:  # ArduPilot's -I N: every port the run owns, + 10 N
        d["mavlink"]["base_port"] += shift
        d["mavlink"]["gcs"] = _shift_port(d["mavlink"]["gcs"], shift)
        d["bus"]["listen"] = _shift_port(d["bus"]["listen"], shift)
    if args.gcs is not None:
        d["mavlink"]["gcs"] = args.gcs
    if args.no_mavlink:
        d["mavlink"]["enabled"] = False
    from sitl.scenario import to_toml_like
    try:
        return scenario_from_dict(to_toml_like(d), scn.source + " + command line")
    except ScenarioError as e:
        msg = str(e).replace("scenario: bus.zenoh", "--zenoh").replace("scenario: mavlink.gcs", "--gcs")
        if args.instance or args.base_port is not None:
            msg = msg.replace("scenario: mavlink.base_port", "--base-port / --instance")
        raise UsageError(msg) from None


def run_main(args) -> int:
    from sitl.scenario import ScenarioError, load_scenario
    opts = options_of(RunOptions, args)
    try:
        scn = load_scenario(opts.scenario)
    except ScenarioError as e:
        raise UsageError(str(e)) from None
    return _main(_scenario_with_overrides(scn, opts), opts)


def demo_main(args) -> int:
    from sitl.scenario import default_scenario
    opts = options_of(DemoOptions, args)
    return _main(_scenario_with_overrides(default_scenario(), opts), opts)


def _main(scn, args: DemoOptions) -> int:
    from sitl.app.experiments.common import prepare_out
    from sitl.app.preflight import OutDirLock, PreflightError, preflight
    out = prepare_out(Path(args.out))
    lock = OutDirLock(out)
    try:  # before anything starts: a mistake costs one line and exit 2 (sitl.app.preflight)
        lock.acquire()
        preflight(scn, live=not args.batch)
    except PreflightError as e:
        lock.release()
        raise UsageError(str(e)) from None
    try:
        if args.batch:
            if getattr(args, "host", None):
                raise UsageError("--host: a batch run (--batch) is one process on this host; drop one of them")
            return _batch(scn, out, args)
        if not args.quiet:
            print(start_text(scn, out), file=sys.stderr, flush=True)
        report = launch(scn, out, quiet=args.quiet, hosts=Placements(getattr(args, "host", None)))
        _write_html_report(out)
    finally:
        lock.release()
    print(summary_text(report))
    print(f"report: {out / 'report.json'}")
    if report.get("stopped_early"):
        return 130  # Ctrl-C / SIGTERM: stopped cleanly, as asked
    return 0 if report["ok"] else 1


#: start_text lists every vehicle's own address up to this many vehicles; above, a line per block
START_TEXT_MAX_VEHICLES = 12


def start_text(scn, out: Path) -> str:
    """What a live run says first: where its output goes and how to connect MAVProxy or
    QGroundControl to it (the scenario's real addresses: [mavlink] gcs, base_port, tcp, and
    the MAVLink blocks of sitl.mavlink.blocks: one line per block beyond a few vehicles)."""
    from sitl.mavlink.blocks import MavlinkPlan
    lines = [f"[launcher] output in {out}/: report.json at the end, bus.log, mav_*.tlog, logs/"]
    m = scn.mavlink
    if not m.enabled:
        return "\n".join(lines + ["[launcher] MAVLink is off ([mavlink] enabled = false): no vehicle to connect to"])
    plan = MavlinkPlan.of(scn)
    names = [f"UAV {i + 1}" for i in range(scn.uavs.count)] + (["sonde"] if scn.sonde.enabled else [])
    if plan.n_blocks == 1 and len(names) <= START_TEXT_MAX_VEHICLES:
        host, gport = m.gcs.rsplit(":", 1)
        lines.append(f"[launcher] the vehicles send MAVLink to {m.gcs}: QGroundControl's default UDP link hears them "
                     f"all, or `mavproxy.py --master udpin:{host}:{gport}`" if gport == "14550" else
                     f"[launcher] the vehicles send MAVLink to {m.gcs}: `mavproxy.py --master udpin:{host}:{gport}` "
                     f"(QGroundControl: a UDP link on port {gport})")
        for i, name in enumerate(names):
            port = plan.listen_port(i)
            lines.append(f"[launcher]   {name} (system id {plan.sysid_of(i)}): `mavproxy.py --master "
                         f"udpout:127.0.0.1:{port}`" + (f" or `--master tcp:127.0.0.1:{port}`" if m.tcp else ""))
        return "\n".join(lines)
    lines.append(f"[launcher] MAVLink: {len(names)} vehicles in {plan.n_blocks} block(s), each its own MAVLink network "
                 f"(system ids 1-{plan.block_size}; the ground station is system 250 on every block); a GCS "
                 "connects to one block's GCS port:")
    proto = "udpout/tcp" if m.tcp else "udpout"
    for k in range(1, plan.n_blocks + 1):
        idx = plan.indices(k)
        first, last = idx[0], idx[-1]
        who = f"vehicles {first + 1}-{last + 1}" if last > first else f"vehicle {first + 1}"
        if scn.sonde.enabled and last == len(names) - 1:
            who += " (the last is the sonde)"
        host, gport = plan.gcs_addr(k)
        p0, p1 = plan.listen_port(first), plan.listen_port(last)
        lines.append(f"[launcher]   block {k}: {who} as system ids 1-{len(idx)} -> {host}:{gport}: `mavproxy.py "
                     f"--master udpin:{host}:{gport}`; system id s alone: {proto} 127.0.0.1:{p0} + 10 (s - 1) "
                     f"(..{p1})")
    return "\n".join(lines)


def _batch(scn, out: Path, args: DemoOptions) -> int:
    from sitl.app.batch import run_batch
    from sitl.app.progress import progress_printer
    from sitl.app.provenance import write_json
    t0 = perf_now()
    # the bus log as a live run's (the report's map and tracks, `skyfuse export`, are read from it)
    res = run_batch(scn, progress=progress_printer(args.quiet, "batch run"),
                    record=out / "bus.log" if scn.bus.log else None)
    doc = {"mode": "batch", "scenario": scn.to_dict(), "wall_s": perf_now() - t0, "errors": res["errors"],
           "ground_station": res["gs"], "published": res["published"], "ok": True}
    if "faults" in res:
        doc["faults"] = res["faults"]
    write_json(out / "report.json", doc, seed=scn.run.seed, scenario=scn)  # + schema, provenance
    _write_html_report(out)
    print(summary_text(doc))
    print(f"report: {out / 'report.json'}")
    if "faults" in res:
        f = res["faults"]
        print(f"  network faults (batch): {len(f['bus_rules'])} bus rule(s) applied, "
              f"{f['injected'].get('dropped_loss', 0)} lost, {f['injected'].get('dropped_partition', 0)} partitioned; "
              f"live-only links not applied: {', '.join(f['not_in_batch']) or 'none'}")
    return 0


def _write_html_report(out: Path) -> None:
    """OUT/report.html from OUT/report.json (sitl.app.report); a report that cannot be made costs
    one line on stderr, never the run's result."""
    from sitl.app.report import ReportError, write_report
    try:
        path = write_report(out)
    except (ReportError, OSError, ValueError, KeyError) as e:
        print(f"[launcher] report.html not written: {' '.join(str(e).split())}", file=sys.stderr)
        return
    print(f"[launcher] report: {path}", file=sys.stderr)


# ---------------------------------------------------------------------- the live run


def launch(scn, out: Path, *, quiet: bool = False, stop: threading.Event | None = None,
           status_stream=None, ready_timeout_s: float = READY_TIMEOUT_S, on_started=None,
           warm_up: bool = True, hosts=None) -> dict:
    """Run the scenario live (module docstring); returns the report (also OUT/report.json).

    stop: set it to stop early (the CLI sets it on SIGINT / SIGTERM). on_started(supervisor):
    called once the workers have started their run (tests use it to inject faults). hosts: a
    sitl.app.hosts.Placements -- the workers started on other hosts through a command."""
    from sitl.bus.buslog import BusRecorder
    from sitl.bus.zenoh_transport import ZenohTransport
    from sitl.app.provenance import write_json
    from sitl.app.scoring import ErrorTracker
    from sitl.app.status import StatusBoard, format_status
    from sitl.app.supervisor import Supervisor
    from sitl.app.components import gs_spec_params
    from sitl.bus.audit import PayloadAudit
    from sitl.scenario import worker_specs

    stop = stop if stop is not None else threading.Event()
    status_stream = status_stream if status_stream is not None else sys.stderr
    tty = hasattr(status_stream, "isatty") and status_stream.isatty()
    restore = _install_signals(stop)
    run = scn.run
    t_wall0 = perf_now()
    router = bus = recorder = sup = live_faults = run_bar = None

    def say(line: str) -> None:  # an event line: above the run's bar once there is one
        if run_bar is not None:
            run_bar(line)
        else:
            _say(status_stream, tty, line)
    audit = PayloadAudit()  # every payload of the run, on every key, counted once
    paced: list = []  # the run's Pacer once it has started: the launcher's simulation clock

    def sim_clock() -> float:  # the clock the bus log stamps and the scorer guards with
        return paced[0].sim_now() if paced else -math.inf
    fault_board = run_json = None
    report: dict = {"mode": "live", "scenario": scn.to_dict(), "ok": False, "events": []}
    shutdown = {}
    try:
        clear_previous_tlogs(out)
        if warm_up and not _cold_warm_up(scn, out, stop, None if quiet else status_stream):
            report["error"] = ("stopped while compiling the kernels" if stop.is_set()
                               else f"the kernels' warm-up failed (see {out / 'logs' / 'warm_up.stderr.log'})")
            return report
        from sitl.bus.zconfig import ZenohConfigError
        from sitl.bus.router import Router, RouterError
        from sitl.bus.zenoh_transport import ZenohTransportError
        try:
            if scn.bus.zenoh:
                endpoints = list(scn.bus.zenoh)
            else:
                router = Router(listen=[scn.bus.listen], lease_ms=scn.bus.lease_ms)
                endpoints = router.endpoints
            report["zenoh"] = endpoints
            bus = ZenohTransport(connect=endpoints, mode="client", lease_ms=scn.bus.lease_ms)
        except (RouterError, ZenohTransportError, ZenohConfigError) as e:
            report["error"] = " ".join(str(e).split())
            return report
        from sitl.bus.faultctl import NoFaultBoard, serve
        if scn.faults:
            from sitl.app.live_faults import LiveFaults
            try:
                live_faults = LiveFaults(scn, endpoints)
            except (OSError, ValueError) as e:
                report["error"] = "network faults: " + " ".join(str(e).split())
                return report
            fault_board = live_faults.board
        else:
            fault_board = NoFaultBoard()
        serve(fault_board, bus, run.id, on_line=lambda line: say(line))
        run_json = _RunJson(out / "run.json", run.id, endpoints, fault_board)
        run_json.write()
        fault_board.on_change = run_json.write
        scorer = ErrorTracker(t0_gps_s=run.t0_gps_s, clock=sim_clock, max_ahead_s=scn.ground_station.max_ahead_s)
        scorer.subscribe(bus, run.id)
        bus.subscribe_raw(f"{run.id}/**", audit)
        if scn.bus.log:  # stamped with the launcher's simulation clock (what replay guards with)
            recorder = BusRecorder(bus, out / "bus.log", key_expr=f"{run.id}/**", append=False,
                                   clock=lambda: max(sim_clock(), run.t0_gps_s))
        (out / "scenario.json").write_text(json.dumps(scn.to_dict(), indent=1))
        spec_dir = out / "specs"
        spec_dir.mkdir(exist_ok=True)
        sup = Supervisor(out / "logs", grace_s=3.0)  # closing a Zenoh session + interpreter exit: ~1 s
        spec_paths = []
        specs = worker_specs(scn, endpoints, out, live_faults.overrides if live_faults is not None else None)
        if hosts and hosts.unmatched(s.name for s in specs):
            report["error"] = (f"--host: no worker matches {', '.join(hosts.unmatched(s.name for s in specs))} "
                               f"(the workers: {', '.join(s.name for s in specs)})")
            return report
        report["hosts"] = {}
        for spec in specs:
            if spec.role == "ground_station":
                spec = dataclasses.replace(spec, params=gs_spec_params(scn))
            path = spec.write(spec_dir / f"{spec.name}.json")
            spec_paths.append(path)
            through = hosts.command_for(spec.name) if hosts else ()
            if through:  # on another host (sitl.app.hosts): the same line protocol over the command's stdio
                report["hosts"][spec.name] = shlex.join(through)
                sup.add(spec.name, [*through, sys.executable, "-m", spec.module, str(path)], restart=True)
            else:
                sup.add_module(spec.name, spec.module, str(path), restart=True)
        if live_faults is not None:  # a restarted worker starts with the bus rules of the moment
            fault_board.on_change = lambda: (run_json.write(), live_faults.respec(spec_paths))
        sup.start_all()
        ready = sup.wait_ready(ready_timeout_s, stop)
        if not ready:
            sup.poll()
            fatal = [f"{c.name}: {c.fatal}" for c in sup.children.values() if c.fatal]
            dead = [f"{c.name} exited with {c.exits[-1]} before it was ready (see {c.stderr_path})"
                    for c in sup.children.values() if c.exits and not c.ready.is_set() and not c.fatal]
            if stop.is_set():
                report["error"] = "stopped before the workers were ready"
            elif fatal or dead:
                report["error"] = "; ".join(fatal + dead)
            else:
                report["error"] = (f"workers not ready after {ready_timeout_s:.0f} s: " +
                                   ", ".join(c.name for c in sup.children.values() if not c.ready.is_set()))
            return report
        wall_start = wall_now() + 0.2
        if live_faults is not None:
            live_faults.start(wall_start)
        sup.broadcast_start(wall_start)
        pacer = Pacer(run.speed, run.t0_gps_s, wall_start, stop=stop)
        paced.append(pacer)
        t_end = run.t0_gps_s + run.duration_s
        if on_started is not None:
            sup.zenoh_endpoints = list(endpoints)
            sup.fault_board = fault_board
            sup.live_faults = live_faults
            on_started(sup)
        board = StatusBoard()
        next_status = perf_now()
        last_line = ""
        if not quiet:  # the run's progress, simulated seconds of the run's duration (tqdm: rate, ETA)
            from sitl.app.progress import Progress
            run_bar = Progress("[launcher] run", stream=status_stream, tty=tty, unit="sim s")
        while not stop.is_set():
            bus.drain()
            for ev in sup.poll():
                if ev["event"] in ("restart", "gave_up") or (ev["event"] == "exit" and not ev.get("clean")):
                    say(f"[launcher] {ev['worker']}: {_event_text(ev)}")
                if ev["event"] == "fatal":
                    report["error"] = f"{ev['worker']}: {ev['error']}"
            fatal = next((c for c in sup.children.values() if c.fatal), None)
            if fatal is not None:
                report.setdefault("error", f"{fatal.name}: {fatal.fatal}")
                break
            if sup.all_finished():
                break
            if pacer.sim_now() > t_end + END_GRACE_WALL_S * run.speed:
                report["error"] = "workers did not finish in time"
                break
            if perf_now() >= next_status:
                next_status += 1.0
                last_line = format_status(board.snapshot(sup, scorer, audit, min(pacer.sim_now(), t_end)), run.t0_gps_s,
                                          run.duration_s, scn.ground_station.stale_after_s)
                if run_bar is not None:
                    run_bar(last_line, done=min(pacer.sim_now(), t_end) - run.t0_gps_s, total=run.duration_s)
            stop.wait(0.05)
        bus.drain()
        report["stopped_early"] = stop.is_set()
        report["last_status"] = last_line
    finally:
        if sup is not None:
            shutdown = sup.stop()
        if live_faults is not None:
            try:
                report["faults"] = live_faults.report(sup)
            finally:
                live_faults.close()
        elif fault_board is not None:
            report["faults"] = fault_board.report()
        if fault_board is not None:
            fault_board.on_change = None
        if run_json is not None:
            run_json.write(finished=True)
        if recorder is not None:
            recorder.close()
        if bus is not None:
            bus.drain()
            bus.close()
        if router is not None:
            router.close()
        _restore_signals(restore)
        if run_bar is not None:
            run_bar.close()
        report["wall_s"] = perf_now() - t_wall0
        from sitl.pacing import cpu_now
        report["launcher_cpu_s"] = cpu_now()  # this process: the embedded router, the log, the scorer
        report["shutdown"] = shutdown
        if sup is not None:
            _fill_report(report, sup, scorer if bus is not None else None, audit, recorder)
        write_json(out / "report.json", report, seed=scn.run.seed, scenario=scn)  # + schema, provenance
    return report


def clear_previous_tlogs(out: Path) -> list[Path]:
    """One tlog per run per link: before a run's workers start, the tlogs a previous run left in a
    re-used output directory (the run holds its lock) are removed, so neither a restart's
    mav_<name>.r<k>.tlog files nor appends pile up across runs. Returns the files removed."""
    gone = sorted(out.glob("mav_*.tlog"))
    for p in gone:
        p.unlink(missing_ok=True)
    return gone


class _RunJson:
    """OUT/run.json: where `skyfuse fault set` finds the running launcher (router endpoints,
    run id, links and their current faults); rewritten on every change, ``finished`` at the end."""

    def __init__(self, path: Path, run_id: str, endpoints: list, board):
        self.path, self.run_id, self.endpoints, self.board = path, run_id, list(endpoints), board

    def write(self, finished: bool = False) -> None:
        doc = {"run_id": self.run_id, "zenoh": self.endpoints, "pid": os.getpid(), "finished": finished,
               "links": sorted(self.board.links), "faults": self.board.current()}
        tmp = self.path.with_suffix(".json.tmp")
        try:
            tmp.write_text(json.dumps(doc, indent=1))
            os.replace(tmp, self.path)
        except OSError as e:  # the run goes on without it
            print(f"[launcher] cannot write {self.path}: {e}", file=sys.stderr)


def _cold_warm_up(scn, out: Path, stop: threading.Event, say) -> bool:
    """numba's on-disk cache warm (sitl.app.kernel_cache): nothing to do, the workers load
    their kernels in a second. Cold (first run, caches deleted, a source changed): a few batch
    epochs of the scenario in a subprocess fill it before any worker starts (so that no worker
    compiles in the middle of the run, nor three processes the same kernels at once), with a
    line at once saying so and how long it will take, and its progress. False if it failed or
    a stop came."""
    import subprocess

    from sitl.app import kernel_cache as kc
    from sitl.runtime import child_env
    if kc.is_warm():
        return True
    est_s, est_n = kc.estimate()
    (out / "logs").mkdir(parents=True, exist_ok=True)
    (out / "scenario.json").write_text(json.dumps(scn.to_dict(), indent=1))
    bar = None
    if say is not None:  # a bar of the kernels compiled against the last cold warm-up's count (tqdm)
        from sitl.app.progress import Progress
        bar = Progress("[launcher] compiling", stream=say, unit="kernel")
        bar(f"[launcher] compiling the estimation kernels (first run only, about {est_s:.0f} s; "
            f"the first run after an install or a source change, later starts skip this)")
        bar(done=0, total=est_n)
    t0, w0 = perf_now(), wall_now() - 1.0
    with open(out / "logs" / "warm_up.stderr.log", "ab") as err:
        p = subprocess.Popen([sys.executable, "-m", "sitl.app.batch", str(out / "scenario.json"), "--warm-up"],
                             stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=err, env=child_env())
    next_poll = perf_now() + 1.0
    try:
        while p.poll() is None:
            if stop.wait(0.2):
                return False
            if bar is not None and perf_now() >= next_poll:
                next_poll += 1.0
                n = kc.written_since(w0)
                bar(done=n, total=max(est_n, n))
    finally:
        if p.poll() is None:
            p.kill()
        p.wait()
        if bar is not None:
            bar.close()
    if p.returncode != 0:
        return False
    el, n = perf_now() - t0, kc.written_since(w0)
    kc.mark_warm(el, n)
    if say is not None:
        _say(say, False, f"[launcher] kernels compiled ({n}) in {el:.0f} s")
    return True


def _fill_report(report, sup, scorer, audit, recorder) -> None:
    from sitl.app.status import run_rejected
    workers = {}
    sent = 0
    for c in sup.children.values():
        statuses = c.history + ([c.status] if c.status and c.status not in c.history else [])
        for st in statuses:
            sent += int(st.get("sent", 0))
        workers[c.name] = {"restarts": c.restarts, "exits": c.exits, "done": c.done, "last": c.status,
                           "stderr": str(c.stderr_path) if c.stderr_path else None, "bad_lines": c.bad_lines}
    report["workers"] = workers
    report["events"] = sup.events
    report["messages_sent"] = sent
    report["rejected"] = dict(run_rejected(sup, audit))
    report["bus_payloads"] = audit.as_dict()  # per key kind: accepted, rejected by reason (every key)
    gs_done = (sup.children.get("gs").last_done if sup.children.get("gs") is not None else {}) or {}
    if gs_done.get("gs", {}).get("links"):  # the ground station's view of each input link, restarts included
        report["links"] = gs_done["gs"]["links"]
    if scorer is not None and scorer.rejected:
        report["scorer_rejected"] = scorer.rejected  # truths / estimates outside the scorer's time window
    report["restarts"] = int(sup.counters.get("restarts", 0))
    report["errors"] = scorer.summary() if scorer is not None else {}
    if scorer is not None:  # (t - t0, error) per target, at most ~600 points each
        series = {}
        for (kind, tid), pts in dict(scorer.series).items():
            step = max(1, len(pts) // 600)
            t0 = scorer.t0 or 0.0
            series[f"{kind}/{tid}"] = [[round(t - t0, 3), round(e, 3)] for t, e in pts[::step]]
        report["error_series"] = series
    report["bus_log"] = ({"records": recorder.records, "errors": recorder.errors, "oversize_not_recorded": recorder.oversize}
                         if recorder is not None else None)
    clean = all(c.done and c.exits and c.exits[-1] == 0 for c in sup.children.values())
    report["orphans"] = sup.alive()
    report["ok"] = (clean or report.get("stopped_early", False)) and not report["orphans"] and "error" not in report


def _event_text(ev) -> str:
    if ev["event"] == "restart":
        return f"died (exit {ev.get('after_returncode')}), restarted (#{ev.get('incarnation')})"
    if ev["event"] == "gave_up":
        return f"died again; not restarted after {ev.get('restarts')} restarts"
    return f"exited with {ev.get('returncode')}"


def _say(stream, tty, line) -> None:
    """One line on ``stream`` (before the run's bar exists, or without one)."""
    try:
        stream.write(line + "\n")
        stream.flush()
    except (OSError, ValueError):
        pass


def _install_signals(stop: threading.Event):
    if threading.current_thread() is not threading.main_thread():
        return None
    old = {}
    for sig in (signal.SIGINT, signal.SIGTERM):
        old[sig] = signal.signal(sig, lambda *_: stop.set())
    return old


def _restore_signals(old) -> None:
    if old:
        for sig, h in old.items():
            signal.signal(sig, h)


def summary_text(report: dict) -> str:
    lines = [f"skyfuse {report.get('mode', 'live')} run: {'ok' if report.get('ok') else 'NOT ok'}"
             + (f" ({report['error']})" if report.get("error") else "")
             + (" (stopped early)" if report.get("stopped_early") else "")]
    if "wall_s" in report:
        lines.append(f"  wall time {report['wall_s']:.1f} s")
    for name, e in sorted((report.get("errors") or {}).items()):
        rm = e.get("rmse_m")
        lines.append(f"  {name:14s} estimates {e.get('estimates', 0):6d}  RMSE "
                     + (f"{rm:10.2f} m" if rm is not None else "        -- m"))
    if "messages_sent" in report:
        lines.append(f"  bus messages sent {report['messages_sent']}, restarts {report.get('restarts', 0)}, "
                     f"rejected inputs {sum((report.get('rejected') or {}).values())}")
        for reason, n in sorted((report.get("rejected") or {}).items()):
            lines.append(f"    rejected {reason}: {n}")
    f = report.get("faults")
    if f and (f.get("links") or f.get("requests")):
        changes = sum(1 for ln in f["links"].values() for h in ln.get("history", []) if h.get("by") == "control")
        lines.append(f"  network faults: {len(f['links'])} links, {changes} changed at run time, "
                     f"{sum(f.get('bad_requests', {}).values())} requests refused"
                     + (f"; not applied (no such link in this run): {', '.join(f['inactive'])}" if f.get("inactive") else ""))
    if report.get("bus_log"):
        lines.append(f"  bus log: {report['bus_log']['records']} records")
    if report.get("orphans"):
        lines.append(f"  ORPHANS: {report['orphans']}")
    return "\n".join(lines)


# ---------------------------------------------------------------------- replay


def replay(log_path, scn, *, use_journal: bool = True) -> dict:
    """The recorded bus log through GroundStationNode on the in-memory transport (module doc):
    with the live ground station's journals beside the log (ground_station.journal) its exact
    inputs and decisions, else (or with ``use_journal=False``) the live rule re-derived on the
    recorder's clock. ``decisions`` in the result says which was used, ``decisions_note`` why."""
    from ground_station.journal import JournalError, find_journals, read_journal_header

    log_path = Path(log_path)
    journals, note = [], ""
    if not use_journal:
        note = "journal not used (asked)"
    else:
        paths = find_journals(log_path.parent)
        if not paths:
            note = "no ground-station journal beside the log"
        for p in paths:
            try:
                hdr = read_journal_header(p)
            except JournalError as e:
                journals, note = [], f"journal not usable: {' '.join(str(e).split())}"
                break
            if hdr["run_id"] != scn.run.id:
                journals, note = [], f"journal {p.name} is of run {hdr['run_id']!r}, not {scn.run.id!r}"
                break
            journals.append(p)
    if journals:
        return _replay_journals(log_path, scn, journals)
    out = _replay_recorder_clock(log_path, scn)
    out["decisions"], out["decisions_note"] = "recorder clock", note
    return out


def _vs_live(replayed: dict, recorded: dict) -> dict:
    """Per estimate kind: replayed, recorded, matched (the same key and time in both) and the
    largest / median position difference of the matched ones. Keys: (..., key, t)."""
    import numpy as np

    def kind_of(k):
        return k[-2].rsplit("/", 2)[-2]

    diffs = {}
    for k, est in replayed.items():
        rec_est = recorded.get(k)
        if rec_est is None:
            continue
        diffs.setdefault(kind_of(k), []).append(float(np.linalg.norm(est.pos_ecef_m - rec_est.pos_ecef_m)))
    cmp = {}
    for kind in sorted({kind_of(k) for k in set(replayed) | set(recorded)}):
        d = np.array(diffs.get(kind, []))
        cmp[kind] = {"replayed": sum(1 for k in replayed if kind_of(k) == kind),
                     "recorded": sum(1 for k in recorded if kind_of(k) == kind),
                     "matched": int(d.size),
                     "max_pos_diff_m": float(d.max()) if d.size else None,
                     "median_pos_diff_m": float(np.median(d)) if d.size else None}
    return cmp


def _replay_recorder_clock(log_path, scn) -> dict:
    """The live rule re-derived from the recorder's receive times (no journal)."""
    from sitl.bus import BusDecodeError, InMemoryTransport, decode, key_matches
    from sitl.bus.buslog import BusLogStats, read_bus_log_records
    from ground_station import node as gn
    from sitl.app.components import gs_config
    from sitl.app.scoring import ErrorTracker

    run_id = scn.run.id
    bus = InMemoryTransport(synchronous=True, start_t_gps_s=scn.run.t0_gps_s)
    clock = [-math.inf]  # the recorded clock: the current record's receive time
    # keep_s: the live scorer's default; the truth table is pruned as live
    scorer = ErrorTracker(t0_gps_s=scn.run.t0_gps_s, clock=lambda: clock[0],
                          max_ahead_s=scn.ground_station.max_ahead_s)
    bus.subscribe(f"{run_id}/truth/**", scorer.on_truth)
    node = gn.GroundStationNode(bus, run_id, gs_config(scn))
    replayed = {}
    bus.subscribe(f"{run_id}/gs/estimate/**", lambda k, m: replayed.__setitem__((k, round(m.t_gps_s, 6)), m))
    bus.subscribe(f"{run_id}/gs/estimate/**", scorer.on_estimate)
    recorded = {}
    stats = BusLogStats()
    hold_sim = scn.ground_station.hold_wall_s * scn.run.speed
    early_window = 2.5 / scn.run.rate_hz  # as ground_station.process
    n = bad = other = 0
    inputs = (f"{run_id}/uav/*/beacon/*", f"{run_id}/sonde/*/relay", f"{run_id}/radar/*/sonde/*")
    for rec in read_bus_log_records(log_path, stats=stats):
        n += 1
        key, payload = rec.key, rec.payload
        if rec.t_recv_s > clock[0]:
            clock[0] = rec.t_recv_s
        try:
            msg = decode(payload)
        except BusDecodeError:
            bad += 1
            bus.publish_raw(key, payload)  # rejected and counted by the transport, as live
            continue
        if key_matches(f"{run_id}/gs/estimate/**", key):
            recorded[(key, round(msg.t_gps_s, 6))] = msg
            continue
        if key_matches(f"{run_id}/truth/**", key):
            bus.publish_raw(key, payload, clock[0])  # published at the record's time, never the payload's
            continue
        if not any(key_matches(e, key) for e in inputs):
            other += 1
            continue
        now = clock[0]  # the live rule, on the clock the live ground station had: taken in, then
        bus.publish_raw(key, payload, now)  # every epoch complete or held long enough is processed
        node.advance(now - hold_sim - 1e-6, early_window_s=early_window, now_s=now)
    node.flush()
    out = {"mode": "replay", "log": str(log_path), "records": n, "undecodable": bad, "other_keys": other,
           "torn_tail": {"dropped_bytes": stats.dropped_bytes, "reason": stats.reason},
           "errors": scorer.summary(), "vs_live": _vs_live(replayed, recorded), "ground_station": node.stats(),
           "bus_rejected": dict(bus.stats.total.rejected), "scorer_rejected": scorer.rejected, "ok": True}
    node.close()
    bus.close()
    return out


def _replay_journals(log_path, scn, journals) -> dict:
    """Each ground-station incarnation's journal through a node of its own configuration and
    incarnation: its inputs as it took them in, its advance() calls with their arguments -- the
    live decisions, bit for bit. The bus log gives the recorded truth (scored against, on the
    journal's clock) and the live estimates (compared with per incarnation, key and time)."""
    from collections import Counter

    from sitl.bus import BusDecodeError, InMemoryTransport, decode, key_matches
    from sitl.bus.buslog import BusLogError, BusLogStats, read_bus_log_records
    from ground_station import node as gn
    from ground_station.journal import (RESUME_KEY, JournalAdvance, JournalError, JournalStats, config_from_json,
                                        read_journal, resume)
    from sitl.app.scoring import ErrorTracker

    run_id = scn.run.id
    clock = [-math.inf]  # the journal's clock (the live ground station's)
    scorer = ErrorTracker(t0_gps_s=scn.run.t0_gps_s, clock=lambda: clock[0],
                          max_ahead_s=scn.ground_station.max_ahead_s)
    truth_bus = InMemoryTransport(synchronous=True, start_t_gps_s=scn.run.t0_gps_s)
    truth_bus.subscribe(f"{run_id}/truth/**", scorer.on_truth)
    stats = BusLogStats()
    records = iter(read_bus_log_records(log_path, stats=stats))
    pending = [None]  # the next bus-log record not yet taken
    counts = {"records": 0, "undecodable": 0, "other_keys": 0}
    recorded = {}

    def take_log(until_s: float) -> None:
        """The bus log's records received up to until_s: truth to the scorer, the live estimates."""
        while True:
            rec = pending[0] if pending[0] is not None else next(records, None)
            pending[0] = None
            if rec is None:
                return
            if rec.t_recv_s > until_s:
                pending[0] = rec
                return
            counts["records"] += 1
            clock[0] = max(clock[0], rec.t_recv_s)
            try:
                msg = decode(rec.payload)
            except BusDecodeError:
                counts["undecodable"] += 1
                continue
            if key_matches(f"{run_id}/gs/estimate/**", rec.key):
                recorded[(int(msg.incarnation), rec.key, round(msg.t_gps_s, 6))] = msg
            elif key_matches(f"{run_id}/truth/**", rec.key):
                truth_bus.publish_raw(rec.key, rec.payload, max(rec.t_recv_s, truth_bus.now_s))
            else:
                counts["other_keys"] += 1

    replayed = {}
    used, gs_stats, bus_rejected, step_errors = [], [], Counter(), 0
    for path in journals:
        jst = JournalStats(path=str(path))
        try:
            events = read_journal(path, jst)
            first = next(events, None)
            config = config_from_json(jst.header["config"])
        except JournalError as e:  # checked before: a file changed meanwhile
            raise BusLogError(str(e)) from None
        inc = int(jst.header["incarnation"])
        bus = InMemoryTransport(synchronous=True, start_t_gps_s=scn.run.t0_gps_s)
        node = gn.GroundStationNode(bus, jst.header["run_id"], config, incarnation=inc)
        if jst.header.get(RESUME_KEY):  # a restart resumed from the earlier journals: so does its replay
            resume(node, [path.parent / name for name in jst.header[RESUME_KEY]])

        def on_estimate(k, m, inc=inc):
            replayed[(inc, k, round(m.t_gps_s, 6))] = m
            scorer.on_estimate(k, m)
        bus.subscribe(f"{run_id}/gs/estimate/**", on_estimate)
        ev = first
        while ev is not None:
            if ev.t_s > clock[0]:
                clock[0] = ev.t_s
                take_log(clock[0])
            if isinstance(ev, JournalAdvance):
                try:  # as live: a failing step is counted and the node goes on
                    node.advance(ev.t_until_s, early_window_s=ev.early_window_s, now_s=ev.now_s)
                except Exception:
                    step_errors += 1
                node.events.clear()
                node.link_changes.clear()
                node.link_messages.clear()
            else:
                bus.publish_raw(ev.key, ev.payload, max(ev.t_s, bus.now_s))  # rejected and counted as live
            ev = next(events, None)
        if jst.bad:
            print(f"replay: journal {path.name}: {sum(jst.bad.values())} bad records skipped "
                  f"({', '.join(f'{r}: {n}' for r, n in sorted(jst.bad.items()))})", file=sys.stderr)
        used.append(jst.as_dict())
        gs_stats.append(node.stats())
        bus_rejected.update(bus.stats.total.rejected)
        node.close()
        bus.close()
    take_log(math.inf)
    torn = [j for j in used if j["torn_tail"]["dropped_bytes"]]
    note = f"{len(used)} ground-station journal{'s' if len(used) > 1 else ''}: " + ", ".join(
        f"{Path(j['path']).name} ({j['inputs']} inputs, {j['advances']} steps)" for j in used)
    if torn:
        note += "; torn tail cut: " + ", ".join(f"{Path(j['path']).name} {j['torn_tail']['dropped_bytes']} bytes "
                                                f"({j['torn_tail']['reason']})" for j in torn)
    out = {"mode": "replay", "log": str(log_path), **counts,
           "torn_tail": {"dropped_bytes": stats.dropped_bytes, "reason": stats.reason},
           "decisions": "journal", "decisions_note": note, "journals": used,
           "errors": scorer.summary(), "vs_live": _vs_live(replayed, recorded),
           "ground_station": gs_stats[0] if len(gs_stats) == 1 else gs_stats, "step_errors": step_errors,
           "bus_rejected": dict(bus_rejected), "scorer_rejected": scorer.rejected, "ok": True}
    truth_bus.close()
    return out


def replay_main(args) -> int:
    from sitl.app.experiments.common import strict
    from sitl.scenario import (
        ScenarioError,
        default_scenario,
        load_scenario,
        scenario_from_dict,
    )
    args = options_of(ReplayOptions, args)
    log = Path(args.log)
    if not log.is_file():
        raise UsageError(f"replay: {str(log)!r}: no such file")
    try:
        if args.scenario is not None:
            scn = load_scenario(args.scenario)
        elif (log.parent / "scenario.json").is_file():
            scn = scenario_from_dict(json.loads((log.parent / "scenario.json").read_text()), "scenario.json")
        else:
            scn = default_scenario()
    except (ScenarioError, ValueError) as e:
        raise UsageError(str(e)) from None
    from sitl.bus.buslog import BusLogError
    try:
        res = replay(log, scn, use_journal=not args.no_journal)
    except BusLogError as e:
        raise UsageError(f"replay: {e}") from None
    if res["records"] == 0:
        raise UsageError(f"replay: {str(log)!r} holds no records"
                       + (f" ({res['torn_tail']['reason']})" if res["torn_tail"]["reason"] else ""))
    lines = [f"replay of {log}: {res['records']} records ({res['undecodable']} undecodable)",
             f"  decisions: {res['decisions']}" + (f" ({res['decisions_note']})" if res["decisions_note"] else "")]
    for name, e in sorted(res["errors"].items()):
        rm = e.get("rmse_m")
        lines.append(f"  {name:14s} estimates {e['estimates']:6d}  RMSE " + (f"{rm:.2f} m" if rm is not None else "--"))
    for kind, c in res["vs_live"].items():
        md = c["max_pos_diff_m"]
        lines.append(f"  {kind:14s} vs live: {c['matched']} of {c['recorded']} recorded estimates matched, "
                     f"max |diff| " + (f"{md:.3g} m" if md is not None else "--"))
    print("\n".join(lines))
    if args.json is not None:
        Path(args.json).write_text(json.dumps(strict(res), indent=1, allow_nan=False))
    return 0
