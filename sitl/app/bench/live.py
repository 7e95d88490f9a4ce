"""`skyfuse bench live`: how large a swarm the live SITL keeps at real time.

For each swarm size N (``--uavs``), a live run of the default scenario's UAVs and beacon
(no sonde) at ``--rate`` Hz and speed 1 for ``--duration`` simulated seconds: a Zenoh router
(started here), the vehicle worker(s) (N UAVs stepped as arrays, each a MAVLink endpoint on
real UDP unless --no-mavlink; beyond 249 UAVs in several MAVLink blocks, sitl.mavlink.blocks,
each block streaming to a UDP sink of its own here) and the ground-station worker.

Per size:
  * ``kept_real_time``: every vehicle worker ran every epoch on time -- no epoch skipped,
    at most 1 % of the epochs more than one epoch late, its per-epoch work p99 under the
    epoch (1 / rate) -- and the ground station's tick (drain + fuse + publish) p90 under the
    epoch (p90, not p99: the locator's one-off start from a window of epochs, ~1 s at 200 UAVs,
    is one of the run's ~100 ticks);
  * ``bus_latency_ms``: p50 / p99 / max of probe messages (UavNav-sized, 100 per second)
    published by one client session and received by another through the same router while
    the run loads it: the publish -> receive time a ground-station session sees at that load
    (both probe sessions live in this process, so one clock times them);
  * ``cpu_ms_per_uav_s``: CPU time of the vehicle workers per UAV per simulated second
    (at speed 1, x 1e-3 = the share of a core one UAV costs), and the same for the ground
    station;
  * ``command_ack_ms`` (MAVLink on): COMMAND_LONG -> COMMAND_ACK round trips of a GCS socket
    to 8 vehicles spread over the swarm, 10 commands a second, p50 / p95 / max (a reply is due
    within one MAVLink epoch);
  * the workers' own figures (step_ms, tick_ms, messages sent), and where a vehicle worker's
    world tick goes (``vehicle_tick_parts_ms``, p50 / p99 of each part: MAVLink input, the
    world's step, its bus puts, the MAVLink streams, and the thread's CPU time over the tick --
    a step p99 well above the CPU p99 is the worker waiting for a core, not its own work).

The largest N that kept real time is the headline (target: >= 200 on 2 cores, bus latency
p99 < 20 ms). The machine's load (``os.getloadavg``) is printed beside: this is a shared
machine. A benchmark, not a test.
"""
from __future__ import annotations

import os
import socket
import sys
import threading
from dataclasses import dataclass
from pathlib import Path

from sitl.app.provenance import options_scenario, write_json
from sitl.app.args import OUTPUT_FILE
from sitl.params import add_flags, from_text, integer, number, optional, param, switch, validate


def _sizes(text: str) -> list[int]:
    import argparse
    try:
        out = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated counts, got {text!r}") from None
    if not out or any(n < 3 for n in out):
        raise argparse.ArgumentTypeError(f"expected counts >= 3, got {text!r}")
    return sorted(set(out))


@dataclass(frozen=True)
class LiveBenchOptions:
    """`skyfuse bench live`'s options, declared once (sitl.params)."""

    uavs: list = param(default_factory=lambda: [50, 100, 200, 300], check=from_text(_sizes, show=lambda v: ",".join(map(str, v))),
                        metavar="N,N,...", doc="swarm sizes to try")
    rate: float = param(10.0, check=number(0, lo_open=True), doc="epochs per second")
    duration: float = param(20.0, check=number(0, lo_open=True), metavar="S", doc="simulated (= wall) seconds per size")
    per_process: int = param(1000, check=integer(lo=1), metavar="N", doc="UAVs per vehicle worker",
                             note=": one vehicle process")
    no_mavlink: bool = param(False, check=switch(), doc="no MAVLink endpoints")
    out: Path = param(Path("out/bench_live"), check=from_text(Path), metavar="DIR", doc="runs' outputs")
    json: Path | None = param(None, check=optional(OUTPUT_FILE), metavar="FILE", doc="also write the result as JSON")

    __post_init__ = validate


def add_args(p) -> None:
    add_flags(p, LiveBenchOptions)


class _Sink(threading.Thread):
    """UDP sockets that read and count what the vehicles send to the GCS addresses: one per
    MAVLink block, on ports ``port + 10 k`` (the blocks' default gcs_port_step)."""

    def __init__(self, n_blocks: int = 1):
        import selectors
        super().__init__(daemon=True)
        self.socks = self._bind(n_blocks)
        self.port = self.socks[0].getsockname()[1]
        self.sel = selectors.DefaultSelector()
        for s in self.socks:
            s.setblocking(False)
            self.sel.register(s, selectors.EVENT_READ)
        self.datagrams = 0
        self.stop = threading.Event()

    @staticmethod
    def _bind(n: int, first: int = 40000, last: int = 60000) -> list:
        for base in range(first, last - 10 * n, 89):
            socks = []
            try:
                for k in range(n):
                    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                    socks.append(s)
                    s.bind(("127.0.0.1", base + 10 * k if n > 1 else 0))
                return socks
            except OSError:
                for s in socks:
                    s.close()
        raise RuntimeError(f"bench live: no {n} free UDP ports 10 apart in {first}..{last} for the GCS sinks")

    def run(self):
        while not self.stop.is_set():
            for key, _ in self.sel.select(0.2):
                for _ in range(256):
                    try:
                        key.fileobj.recv(65535)
                    except (BlockingIOError, InterruptedError):
                        break
                    except OSError:
                        return
                    self.datagrams += 1

    def close(self):
        self.stop.set()
        self.join(1.0)
        self.sel.close()
        for s in self.socks:
            s.close()


class _Probe:
    """Latency probes publish -> receive through the router (module docstring)."""

    def __init__(self, endpoint: str, rate_hz: float = 100.0):
        import numpy as np

        from sitl.bus import UavNav
        from sitl.bus.zenoh_transport import ZenohTransport
        self.pub = ZenohTransport(connect=[endpoint])
        self.sub = ZenohTransport(connect=[endpoint], delivery="callback")
        self.lat: list[float] = []
        self.key = "benchprobe/uav/1/nav"
        self.sub.subscribe(self.key, self._on)
        self._msg = dict(source_id="probe", pos_ecef_m=np.array([6.4e6, 0.0, 0.0]), vel_ecef_m_s=np.zeros(3),
                         cov=np.eye(6), n_sats=8, fix_type=3)
        self._UavNav = UavNav
        self.period = 1.0 / rate_hz
        self.stop = threading.Event()
        self.measure = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _on(self, key, msg):
        from sitl.pacing import perf_now
        if self.measure.is_set():
            self.lat.append(perf_now() - msg.t_gps_s)

    def _run(self):
        from sitl.pacing import perf_now
        k = 0
        while not self.stop.wait(self.period):
            self.pub.publish(self.key, self._UavNav(t_gps_s=perf_now(), seq=k, **self._msg))
            k += 1

    def close(self):
        self.stop.set()
        self._thread.join(2.0)
        self.pub.close()
        self.sub.close()


class _AckProbe(threading.Thread):
    """COMMAND_LONG -> COMMAND_ACK round trips, as a GCS sees them: every ``period_s`` a
    MAV_CMD_GET_MESSAGE_INTERVAL (a harmless command every vehicle answers at once) to the next
    of ``targets`` (system ids spread over the swarm) from a socket of its own (the replies come
    back to it), one outstanding per vehicle; the wall time from send to the ACK, measured while
    ``measure`` is set. A command unanswered within 2 s counts as lost."""

    def __init__(self, targets, base_port: int, measure: threading.Event, period_s: float = 0.1):
        super().__init__(daemon=True)
        from pymavlink.dialects.v20 import ardupilotmega as mavlink
        self.mavlink = mavlink
        self.mav = mavlink.MAVLink(None, srcSystem=254, srcComponent=190)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.02)
        self.targets = list(targets)
        self.base = int(base_port)
        self.measure, self.period_s = measure, float(period_s)
        self.stop = threading.Event()
        self.lat: list[float] = []
        self.sent = self.lost = 0

    def run(self):
        from sitl.pacing import perf_now
        pending: dict = {}
        k, next_send = 0, perf_now()
        while not self.stop.is_set():
            now = perf_now()
            if now >= next_send and self.targets:
                sysid = self.targets[k % len(self.targets)]
                k += 1
                next_send = now + self.period_s
                if sysid in pending and now - pending[sysid] > 2.0:
                    del pending[sysid]
                    self.lost += 1
                if sysid not in pending:
                    buf = self.mav.command_long_encode(sysid, 1, self.mavlink.MAV_CMD_GET_MESSAGE_INTERVAL, 0,
                                                       33, 0, 0, 0, 0, 0, 0).pack(self.mav)
                    self.mav.seq = (self.mav.seq + 1) % 256
                    try:
                        self.sock.sendto(buf, ("127.0.0.1", self.base + 10 * (sysid - 1)))
                    except OSError:
                        continue
                    pending[sysid] = perf_now()
                    if self.measure.is_set():
                        self.sent += 1
            try:
                data = self.sock.recv(65535)
            except (TimeoutError, OSError):
                continue
            t = perf_now()
            try:
                msgs = self.mav.parse_buffer(data) or []
            except self.mavlink.MAVError:
                continue
            for m in msgs:
                if m.get_type() == "COMMAND_ACK" and m.command == self.mavlink.MAV_CMD_GET_MESSAGE_INTERVAL:
                    t0 = pending.pop(m.get_srcSystem(), None)
                    if t0 is not None and self.measure.is_set():
                        self.lat.append(t - t0)

    def close(self):
        self.stop.set()
        self.join(1.0)
        self.sock.close()


def _free_udp_base(n: int, first: int = 20000, last: int = 60000) -> int:
    """A base port with every vehicle port of n vehicles free for UDP (the MAVLink blocks' plan,
    sitl.mavlink.blocks: base + 10 i up to 249 vehicles; a shared machine's tests take some of
    20000+): the first such from ``first``."""
    from sitl.mavlink.blocks import MavlinkPlan

    def free(port):
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            try:
                s.bind(("127.0.0.1", port))
                return True
            except OSError:
                return False
    for base in range(first, last - 10 * min(n, 249) - 10, 97):
        plan = MavlinkPlan(n_vehicles=n, base_port=base)
        if all(free(plan.listen_port(i)) for i in range(n)):
            return base
    raise RuntimeError(f"bench live: no free UDP ports for {n} vehicles' MAVLink in {first}..{last}")


def _pct(values, q):
    if not values:
        return None
    a = sorted(values)
    return a[min(len(a) - 1, int(q * len(a)))]


def run_size(n: int, args, router_ep: str) -> dict:
    from sitl.app.launcher import launch
    from sitl.scenario import default_scenario

    from sitl.constants import MAX_MAVLINK_FLEET, MAX_MAVLINK_VEHICLES
    mav = not args.no_mavlink and n <= MAX_MAVLINK_FLEET
    sink = _Sink(-(-n // MAX_MAVLINK_VEHICLES)) if mav else None
    if sink is not None:
        sink.start()
    probe = _Probe(router_ep)
    base = _free_udp_base(n if mav else 0)
    # a ring whose radius grows with the swarm (the same spacing), heights in three layers
    scn = default_scenario().replace(
        run={"id": f"bench{n}", "rate_hz": args.rate, "duration_s": args.duration, "speed": 1.0},
        bus={"zenoh": (router_ep,), "log": False},
        uavs={"count": n, "per_process": args.per_process, "radius_m": max(15000.0, 150.0 * n)},
        sonde={"enabled": False},
        mavlink={"enabled": mav, "gcs": f"127.0.0.1:{sink.port if sink else 14550}",
                 "base_port": base, "tlog": False})
    started = threading.Event()
    # GCS commands to 8 vehicles spread over the swarm, 10 a second (MAVLink on)
    acks = (_AckProbe(sorted({1 + (i * (n - 1)) // 7 for i in range(8)}), base, probe.measure)
            if scn.mavlink.enabled else None)

    def on_started(sup):
        started.set()
        if acks is not None:
            acks.start()
        # measure after the first epochs (the start-up transient is not the steady load)
        threading.Timer(min(3.0, args.duration / 4), probe.measure.set).start()

    out = Path(args.out) / f"n{n}"
    out.mkdir(parents=True, exist_ok=True)
    from sitl.pacing import cpu_now
    cpu0 = cpu_now()
    try:
        rep = launch(scn, out, quiet=True, on_started=on_started)
    finally:
        cpu1 = cpu_now()
        probe.measure.clear()
        probe.close()
        if acks is not None:
            acks.close()
        if sink is not None:
            sink.close()
    epochs = int(args.duration * args.rate) + 1
    veh = [w["last"] for name, w in rep.get("workers", {}).items() if name.startswith("vehicles")]
    gs = rep.get("workers", {}).get("gs", {}).get("last", {})
    skipped = sum(int(v.get("skipped_epochs", 0)) for v in veh)
    late = sum(int(v.get("late_epochs", 0)) for v in veh)
    step_p99 = max((v.get("step_ms", {}).get("p99", 0.0) for v in veh), default=None)
    tick_p90 = (gs.get("tick_ms") or {}).get("p90")
    cpu_v = sum(float(v.get("cpu_s", 0.0)) for v in veh)
    kept = (rep.get("ok", False) and skipped == 0 and late <= 0.01 * epochs and step_p99 is not None
            and step_p99 < 1e3 / args.rate and tick_p90 is not None and tick_p90 < 1e3 / args.rate)
    lat = probe.lat
    return {"uavs": n, "mavlink": scn.mavlink.enabled, "kept_real_time": bool(kept), "ok": rep.get("ok", False), "error": rep.get("error"),
            "epochs": epochs, "skipped_epochs": skipped, "late_epochs": late,
            "vehicle_step_ms": [v.get("step_ms") for v in veh], "gs_tick_ms": gs.get("tick_ms"),
            "vehicle_tick_parts_ms": [v.get("tick_parts_ms") for v in veh],
            "bus_latency_ms": {"p50": None if not lat else 1e3 * _pct(lat, 0.5),
                               "p99": None if not lat else 1e3 * _pct(lat, 0.99),
                               "max": None if not lat else 1e3 * max(lat), "probes": len(lat)},
            "command_ack_ms": None if acks is None else {
                "p50": None if not acks.lat else 1e3 * _pct(acks.lat, 0.5),
                "p95": None if not acks.lat else 1e3 * _pct(acks.lat, 0.95),
                "max": None if not acks.lat else 1e3 * max(acks.lat), "answered": len(acks.lat),
                "sent": acks.sent, "lost": acks.lost},
            "cpu_ms_per_uav_s": 1e3 * cpu_v / (n * args.duration),
            "gs_cpu_ms_per_s": 1e3 * float(gs.get("cpu_s", 0.0)) / args.duration,
            # this process during the run: the router, the launcher's session, the probes, start-up
            "router_launcher_cpu_ms_per_s": 1e3 * (cpu1 - cpu0) / max(rep.get("wall_s") or 1.0, 1e-9),
            "messages_sent": rep.get("messages_sent"), "mavlink_datagrams_at_gcs": sink.datagrams if sink else 0,
            "beacon_estimates": (rep.get("errors", {}).get(f"beacon/{scn.beacon.id}") or {}).get("estimates"),
            "load_avg": os.getloadavg(), "wall_s": rep.get("wall_s")}


def main(args) -> int:
    from sitl.bus.router import Router
    from sitl.app.experiments.common import prepare_out

    prepare_out(Path(args.out))
    rows = []
    with Router(listen=["tcp/127.0.0.1:0"]) as router:
        ep = router.endpoints[0]
        for n in args.uavs:
            print(f"[bench live] {n} UAVs at {args.rate:g} Hz for {args.duration:g} s (load {os.getloadavg()[0]:.1f}) ...",
                  file=sys.stderr, flush=True)
            r = run_size(n, args, ep)
            rows.append(r)
            lat = r["bus_latency_ms"]
            print(f"  {n:5d} UAVs{'' if r['mavlink'] else ' (no MAVLink)'}: real time {'kept' if r['kept_real_time'] else 'NOT kept'}; skipped "
                  f"{r['skipped_epochs']}, late {r['late_epochs']} of {r['epochs']} epochs; vehicle step p99 "
                  f"{_fmt([s.get('p99') if s else None for s in r['vehicle_step_ms']])} ms; GS tick p90 "
                  f"{_fmt([(r['gs_tick_ms'] or {}).get('p90')])} ms; bus latency p50/p99 "
                  f"{_fmt([lat['p50']])}/{_fmt([lat['p99']])} ms; CPU {r['cpu_ms_per_uav_s']:.2f} ms per UAV-s "
                  f"(GS {r['gs_cpu_ms_per_s']:.0f} ms/s, router+launcher {r['router_launcher_cpu_ms_per_s']:.0f} ms/s); "
                  f"load {r['load_avg'][0]:.1f}", flush=True)
            ack = r["command_ack_ms"]
            if ack and ack["answered"]:
                print(f"    COMMAND_LONG -> COMMAND_ACK ({ack['answered']} of {ack['sent']} answered, {ack['lost']} lost): "
                      f"p50 {ack['p50']:.1f} ms, p95 {ack['p95']:.1f} ms, max {ack['max']:.1f} ms "
                      f"(one MAVLink epoch: {1e3 / args.rate:.0f} ms)", flush=True)
            for w, tp in enumerate(r["vehicle_tick_parts_ms"]):
                if tp:  # where a world tick's time goes, per vehicle worker (vehicles.process.TICK_PARTS)
                    print(f"    vehicles{w} world tick p50/p99 ms: " + ", ".join(
                        f"{name} {v['p50']:.1f}/{v['p99']:.1f}" for name, v in tp.items()), flush=True)
            if r["error"]:
                print(f"    error: {r['error']}", flush=True)
    kept = [r["uavs"] for r in rows if r["kept_real_time"]]
    best = max(kept) if kept else None
    print(f"largest swarm at real time ({args.rate:g} Hz): {best if best is not None else 'none of ' + str(args.uavs)}"
          f" (target >= 200)")
    doc = {"rate_hz": args.rate, "duration_s": args.duration, "largest_real_time_uavs": best, "runs": rows}
    if args.json is not None:
        write_json(args.json, doc, scenario=options_scenario(args))
    return 0


def _fmt(vals) -> str:
    vals = [v for v in vals if v is not None]
    return "/".join(f"{v:.1f}" for v in vals) if vals else "--"
