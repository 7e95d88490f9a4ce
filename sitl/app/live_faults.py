"""The live launcher's network-fault wiring: proxies, the control board, the report.

When a scenario has a [faults] table (even an empty one), `LiveFaults` starts, in the
launcher, on one shared proxy thread (`sitl.netfault.proxyloop.ProxyLoop`):

* per worker a `TcpProxy` between that worker's Zenoh session and the router: the worker's
  spec connects to the proxy (link ``zenoh:<worker>``: partitions, delay, rate);
* with MAVLink on, per vehicle a `UdpProxy` between its endpoint and the GCS (link
  ``mav:<n>``, n the vehicle's number: its system id in MAVLink block 1; directions ``:up``
  vehicle->GCS and ``:down``; each proxy sends to its vehicle's block's GCS address,
  sitl.mavlink.blocks). The vehicle workers' specs name one front socket as the GCS of every
  block (`MavFront`); the front tells the vehicles apart by their source address (the
  plan's port of each: vehicle i sends from base_port + 10 i in block 1) and hands each one's traffic
  to its proxy from a socket of its own, so replies come back to the right vehicle and the
  vehicles see them come from their GCS address;
* bus-key faults (``bus:<expr>``) are the workers' own publisher filters (`sitl.live.worker`).

Every link is started, with no fault where the scenario names none, so that
``skyfuse fault set`` can add one to any link while the run goes. The board
(`sitl.netfault.control.FaultBoard`) answers the control key; `report` gives the report's
``faults`` block. `close` closes every proxy, the front and the loop (no thread, no port left).

Time (`RunClock`): simulated seconds since the run's start, what a spec's ``partition=T1-T2``
means. Before the start it runs at the run's speed but far below zero (so that the switch to
the run's own clock at the start only ever jumps forward: nothing scheduled waits longer).
"""
from __future__ import annotations

import argparse
import selectors
import socket
from dataclasses import dataclass
from pathlib import Path

from sitl.app.args import add_positional, repeatable
from sitl.app.launcher import DemoOptions, RunOptions
from sitl.pacing import wall_now
from sitl.params import Check, add_flags, default_of, from_text, number, optional, param, several, string, validate

PRESTART_OFFSET_S = 1e6  # simulated seconds below zero before the start (module text)
# the proxies' receiver-side MAVLink tap (pymavlink parses every forwarded datagram: measured
# ~35-70 us each in the launcher, beside ~40-70 us for front + proxy) only up to this many vehicles
MAV_TAP_MAX_VEHICLES = 32
# the MAVLink truths keep their per-packet schedule (~26 B a packet) only while vehicles x
# simulated seconds stays below this (3 vehicles x 2 h at ~15 packets/s: ~8 MB); counters always
MAV_RECORD_MAX_VEHICLE_S = 3 * 7200

# ---------------------------------------------------------------------- `skyfuse fault` arguments
# (the parser is built at every `skyfuse` call: it lives here, light; sitl.app.fault_cli runs it)
# Each subcommand's options are one frozen dataclass declared once (sitl.params.param); add_flags
# gives the flags, sitl.app.args.options_of the instance.

# the live runs' output directories, where `fault` looks for run.json: `demo`'s and `run`'s --out defaults
DEFAULT_OUTS = tuple(str(default_of(c, "out")) for c in (DemoOptions, RunOptions))
TIMEOUT_MAX_S = 3600.0


def _timeout_s() -> Check:
    """Seconds in (0, TIMEOUT_MAX_S): how long `fault` waits for the launcher."""
    return number(0, lo_open=True, hi=TIMEOUT_MAX_S, hi_open=True, what=f"seconds in (0, {TIMEOUT_MAX_S:g})")


@dataclass(frozen=True, kw_only=True)
class FaultListOptions:
    """`skyfuse fault list`'s options: where the run is, how long to wait for its launcher."""

    out: Path | None = param(None, check=optional(from_text(Path)), metavar="DIR", doc="the run's output directory",
                             default_help="its run.json names the router and the run; "
                                          f"default: the newest of {', '.join(DEFAULT_OUTS)}")
    zenoh: list | None = param(None, check=repeatable(string()), metavar="tcp/HOST:PORT",
                               doc="the run's Zenoh router (instead of OUT/run.json; repeatable)")
    run: str | None = param(None, check=optional(string()), metavar="ID", doc="the run id",
                            default_help="default: run.json's, else 'demo'")
    timeout: float = param(5.0, check=_timeout_s(), metavar="S", note=" s",
                           doc="how long to wait for the launcher's answer")

    __post_init__ = validate


@dataclass(frozen=True, kw_only=True)
class FaultSetOptions(FaultListOptions):
    """`skyfuse fault set LINK SPEC...`'s options: the link, its new fault, then `list`'s."""

    link: str = param(check=string(), cli=False,  # positional
                      doc="mav:<sysid>[:up|:down], zenoh:<worker>, bus:<key expression>")
    spec: list = param(check=several(string(), "+"), cli=False,  # positional, one or more words
                       doc='netem-like text, e.g. loss=10% delay=100ms~20ms ("none": no fault)')


def add_fault_args(p: argparse.ArgumentParser) -> None:
    """The `fault` command's subcommands (set, list) on the parser the lead's cli gives."""
    sub = p.add_subparsers(dest="fault_command", metavar="ACTION", parser_class=type(p))
    sub.required = True
    s = sub.add_parser("set", help="change a link's fault while a live run goes",
                       description="Change the network fault of one link of a running live run (0: acknowledged, "
                                   "2: bad spec or unknown link, 1: no launcher answered).")
    add_positional(s, FaultSetOptions, "link")
    add_positional(s, FaultSetOptions, "spec")
    add_flags(s, FaultSetOptions)
    ls = sub.add_parser("list", help="the links of a live run and their current faults",
                        description="List the links of a running live run and their current faults.")
    add_flags(ls, FaultListOptions)


class RunClock:
    """Simulated seconds since the run's start (module text)."""

    def __init__(self, speed: float):
        self.speed = float(speed)
        self._w0 = wall_now()
        self._start: float | None = None

    def start(self, wall_start_s: float) -> None:
        self._start = float(wall_start_s)

    @property
    def started(self) -> bool:
        return self._start is not None

    def __call__(self) -> float:
        if self._start is None:
            return -PRESTART_OFFSET_S + self.speed * (wall_now() - self._w0)
        return self.speed * (wall_now() - self._start)


def _addr(endpoint: str) -> tuple[str, int]:
    """"tcp/HOST:PORT" -> (HOST, PORT)."""
    rest = endpoint.split("/", 1)[1]
    host, _, port = rest.rpartition(":")
    return host.strip("[]"), int(port)


class MavFront:
    """One UDP socket the vehicles take for their GCS; demultiplexes by source address to a
    socket per vehicle that talks to that vehicle's `UdpProxy` (module text). Runs on the
    proxy loop's thread. ``counters``: forwarded each way, ``unknown_source`` (datagrams from
    an address that is no vehicle: dropped), send errors."""

    def __init__(self, loop, vehicles: dict[tuple, tuple]):
        """vehicles: {vehicle endpoint address: its proxy's listen address}."""
        self.loop = loop
        self.counters = {"to_proxy": 0, "to_vehicle": 0, "unknown_source": 0, "send_errors": 0}
        self._front = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._socks: dict[tuple, socket.socket] = {}
        self._by_sock: dict[socket.socket, tuple] = {}
        self._proxy_of: dict[tuple, tuple] = {}
        try:
            self._front.bind(("127.0.0.1", 0))
            self._front.setblocking(False)
            for vaddr, paddr in vehicles.items():
                s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                self._socks[vaddr] = s
                s.bind(("127.0.0.1", 0))
                s.setblocking(False)
                self._by_sock[s] = vaddr
                self._proxy_of[vaddr] = paddr
            self.addr = self._front.getsockname()
            loop.call(self._register)
        except BaseException:
            self._close_sockets()
            raise
        self._closed = False

    def _register(self) -> None:
        self.loop.interest(self._front, selectors.EVENT_READ, self._on_front)
        for s in self._socks.values():
            self.loop.interest(s, selectors.EVENT_READ, lambda _m, s=s: self._on_back(s))

    def _on_front(self, _mask) -> None:
        for _ in range(64):
            try:
                data, src = self._front.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                return
            except OSError as e:
                self.loop.report("mav front: recv", e)
                return
            s = self._socks.get(src)
            if s is None:
                self.counters["unknown_source"] += 1
                continue
            try:
                s.sendto(data, self._proxy_of[src])
                self.counters["to_proxy"] += 1
            except OSError as e:
                self.counters["send_errors"] += 1
                self.loop.report("mav front: send", e)

    def _on_back(self, s) -> None:
        vaddr = self._by_sock[s]
        for _ in range(64):
            try:
                data, _src = s.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                return
            except OSError as e:  # ICMP port unreachable from a vehicle not up yet
                self.loop.report("mav front: recv", e)
                return
            try:
                self._front.sendto(data, vaddr)
                self.counters["to_vehicle"] += 1
            except OSError as e:
                self.counters["send_errors"] += 1
                self.loop.report("mav front: send", e)

    def _close_sockets(self) -> None:
        for s in [self._front, *self._socks.values()]:
            try:
                if not self.loop.closed and self.loop.on_loop_thread:
                    self.loop.forget(s)
                else:
                    s.close()
            except OSError:
                pass

    def close(self) -> None:
        if getattr(self, "_closed", True):
            return
        self._closed = True
        try:
            if not self.loop.closed:
                self.loop.call(self._close_sockets)
        finally:
            self._close_sockets()


class LiveFaults:
    """Everything the launcher runs for the network faults of one live run (module text)."""

    def __init__(self, scn, router_endpoints: list[str]):
        from sitl.netfault.proxyloop import ProxyLoop
        from sitl.netfault.control import FaultBoard
        self.scn = scn
        self.clock = RunClock(scn.run.speed)
        from sitl.scenario import run_keys
        self.board = FaultBoard(self.clock, bus_keys=run_keys(scn))
        self.loop = ProxyLoop(self.clock, scn.run.speed, name="netfault-proxies")
        self.tcp: dict[str, object] = {}  # worker -> TcpProxy
        self.udp: dict[int, object] = {}  # sysid -> UdpProxy
        self.front: MavFront | None = None
        self.overrides: dict[str, dict] = {}  # worker -> WorkerSpec overrides
        try:
            self._start(router_endpoints)
        except BaseException:
            self.close()
            raise

    def _start(self, endpoints: list[str]) -> None:
        import numpy as np

        from sitl.netfault.tcp_proxy import TcpProxy
        from sitl.netfault.udp_proxy import UdpProxy
        scn = self.scn
        faults = scn.faults
        seeds = np.random.SeedSequence([scn.run.seed, 0xFA17])
        target = _addr(endpoints[0])
        workers = scn.worker_names()
        for w, ss in zip(workers, seeds.spawn(len(workers))):
            link = f"zenoh:{w}"
            p = TcpProxy(target, spec=faults.get(link), rng=np.random.default_rng(ss), loop=self.loop, name=link)
            self.tcp[w] = p
            host, port = p.addr[0], p.addr[1]
            self.overrides.setdefault(w, {})["zenoh_connect"] = [f"tcp/{host}:{port}"]
            self.board.add_link(link, lambda spec, t, p=p: p.set(spec),
                                lambda p=p: _tcp_truth(p))
        m = scn.mavlink
        if m.enabled and scn.n_vehicles:
            from sitl.mavlink.blocks import MavlinkPlan
            plan = MavlinkPlan.of(scn)  # each vehicle's proxy goes to its MAVLink block's GCS
            vehicles = {}
            for i, ss in zip(range(scn.n_vehicles), seeds.spawn(scn.n_vehicles)):
                sysid = i + 1  # the link's number: the vehicle's in the run (its system id in block 1)
                link = f"mav:{sysid}"
                both = faults.get(link)
                up, down = faults.get(f"{link}:up", both), faults.get(f"{link}:down", both)
                p = UdpProxy(plan.gcs_addr(plan.block_of(i)), up=up, down=down, rng=np.random.default_rng(ss),
                             loop=self.loop, name=link, tap=scn.n_vehicles <= MAV_TAP_MAX_VEHICLES,
                             record=scn.n_vehicles * scn.run.duration_s <= MAV_RECORD_MAX_VEHICLE_S)
                self.udp[sysid] = p
                vehicles[("127.0.0.1", plan.listen_port(i))] = p.addr
                self.board.add_link(f"{link}:up", lambda spec, t, p=p: p.set(up=spec),
                                    lambda p=p: _udp_truth(p, "up"))
                self.board.add_link(f"{link}:down", lambda spec, t, p=p: p.set(down=spec),
                                    lambda p=p: _udp_truth(p, "down"))
            self.front = MavFront(self.loop, vehicles)
            for w in workers:
                if w != "gs":  # every block to the one front (gcs_port_step 0: sitl.mavlink.blocks)
                    self.overrides.setdefault(w, {})["mavlink_gcs"] = f"{self.front.addr[0]}:{self.front.addr[1]}"
        # what the scenario sets, as the first entry of each link's history (t = 0: the start)
        for name, rec in self.board.links.items():
            kind, _, _rest = name.partition(":")
            text = faults.get(name)
            if text is None and kind == "mav":
                text = faults.get(name.rsplit(":", 1)[0])
            rec.current = _canon(text)
            rec.history.append({"t_s": 0.0, "spec": rec.current, "by": "scenario"})
        for name, text in faults.of_kind("bus"):
            self.board.set(name, text, by="scenario")
            self.board.bus_rules[name].history[-1]["t_s"] = 0.0

    def start(self, wall_start_s: float) -> None:
        self.clock.start(wall_start_s)

    def respec(self, spec_paths) -> None:
        """Write the current bus-key rules into the workers' spec files, so that a worker
        restarted later starts with the rules changed at run time (in KeyFaults' order; a rule
        set to "none" stays, it still takes its keys)."""
        import json
        import os
        b = self.board
        bus = {n: b.bus_rules[n].current for n in b.bus_order}
        for path in spec_paths:
            try:
                doc = json.loads(path.read_text(encoding="utf-8"))
                faults = doc["scenario"].get("faults", {})
                faults = {k: v for k, v in faults.items() if not k.startswith("bus:")}
                doc["scenario"]["faults"] = {**faults, **bus}
                tmp = path.with_suffix(".json.tmp")
                tmp.write_text(json.dumps(doc, indent=1), encoding="utf-8")
                os.replace(tmp, path)
            except (OSError, ValueError, KeyError, TypeError) as e:
                self.loop.report(f"respec {path}", e)

    def links(self) -> list[str]:
        return sorted(self.board.links)

    def report(self, sup=None) -> dict:
        """The report's ``faults`` block (bus-key truths summed over the workers' last status
        lines of every incarnation)."""
        from sitl.netfault.control import add_truths
        bus_truths: dict[str, dict] = {}
        filters: dict[str, dict] = {}
        if sup is not None:
            for c in sup.children.values():
                for nf in getattr(c, "netfault", {}).values():  # the latest of each incarnation
                    for link, t in (nf.get("truth") or {}).items():
                        bus_truths[link] = add_truths(bus_truths.get(link, {}), t)
                    filters[c.name] = add_truths(filters.get(c.name, {}), nf.get("filter") or {})
        out = self.board.report(bus_truths)
        out["bus_filters"] = filters
        # scenario entries with no link in this run (e.g. mav:* with MAVLink off): not applied
        out["inactive"] = [k for k, _ in self.scn.faults.links
                           if not k.startswith("bus:") and k not in self.board.links
                           and not {f"{k}:up", f"{k}:down"} <= set(self.board.links)]
        if self.front is not None:
            out["mav_front"] = dict(self.front.counters)
        out["proxy_errors"] = dict(self.loop.errors)
        return out

    def close(self) -> None:
        for p in list(self.udp.values()) + list(self.tcp.values()):
            try:
                p.close()
            except Exception:
                pass
        if self.front is not None:
            self.front.close()
        self.loop.close()


__all__ = ["LiveFaults", "MavFront", "RunClock", "add_fault_args"]


def _canon(text) -> str:
    from sitl.netfault import parse_spec
    from sitl.netfault.control import spec_text
    return "none" if text is None else spec_text(parse_spec(text))


def _udp_truth(p, direction: str) -> dict:
    from sitl.netfault.control import truth_dict
    if p.closed:
        return getattr(p, "_final_stats", {}).get(direction, {})
    st = getattr(p.stats(), direction)
    d = {"received": st.received, "forwarded": st.forwarded, "send_errors": st.send_errors,
         "no_client": st.no_client, "pending": st.pending, "truth": truth_dict(st.truth)}
    if st.tap is not None:
        d["tap"] = truth_dict(st.tap)
    return d


def _tcp_truth(p) -> dict:
    from sitl.netfault.control import truth_dict
    if p.closed:
        return getattr(p, "_final_stats", {})
    st = p.stats()
    return truth_dict(st)
