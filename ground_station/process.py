"""The ground-station worker of a live run: ``python -m ground_station.process SPEC.json``.

A `GroundStationNode` (the batch beacon locator and sonde tracker) on the run's Zenoh bus,
stepped by the paced clock: every tick it takes in what has arrived and processes the epochs
that are complete (every source publishing has delivered them) or older than
``ground_station.hold_wall_s`` (x speed, in simulated time), publishing the
Estimates on ``<run>/gs/estimate/**``. It also speaks MAVLink to the ground-control
endpoint (pymavlink): the beacon and sonde estimates as ADSB_VEHICLE (so that the GCS map
shows them), the integrity events its trackers publish (``<run>/gs/integrity/**``) and its input links
turning stale or coming back (``<run>/gs/link/**``, "link uav2: stale") as STATUSTEXT, from its
own system id (250, component MAV_COMP_ID_ONBOARD_COMPUTER); ``mav_gs.tlog`` records them.
"""
from __future__ import annotations

import math
import sys
from collections import Counter

GS_SYSID = 250
ADSB_ICAO = {"beacon": 0xB1C000, "sonde": 0x50D000}


class GcsLink:
    """ADSB_VEHICLE and STATUSTEXT to the ground-control endpoint (UDP, pymavlink, MAVLink 2).

    signing_key (32 bytes): every frame is signed (mavlink.io "Message Signing"; link id
    ``link_id``), its timestamp max(previous + 1, clock) -- monotonic within the process, and
    across a restart of the worker as long as the clock (the wall clock by default: the
    launcher's, which a restart does not set back) is: a new incarnation starts at the clock's
    now, past everything the old one sent (its timestamps ran ahead of the clock by one 10 us
    tick per frame only, i.e. never more than ~0.1 s at the rates here).  The link never reads
    what comes back, so no peer timestamp moves it.  clock: unix seconds (injected; default
    sitl.pacing.wall_now).

    ``adsb`` never raises on an estimate: a non-finite or malformed position is not sent
    (``skipped[reason]``); a field MAVLink cannot carry (an altitude beyond int32 mm, a speed
    beyond the int16/uint16 cm/s fields, a non-finite velocity) is clamped or zeroed, its
    ADSB_FLAGS_VALID_* bit cleared, and counted (``clamped[field]``)."""

    def __init__(self, gcs: str, tlog=None, *, signing_key: bytes | None = None, clock=None, link_id: int = 0):
        import socket

        from pymavlink.dialects.v20 import common as m

        from sitl.pacing import wall_now

        host, port = gcs.rsplit(":", 1)
        self.addr = (host, int(port))
        if signing_key is not None and (not isinstance(signing_key, (bytes, bytearray)) or len(signing_key) != 32):
            raise ValueError("signing_key must be 32 bytes")
        self._clock = wall_now if clock is None else clock
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setblocking(False)
        self.mav = m.MAVLink(self, srcSystem=GS_SYSID, srcComponent=m.MAV_COMP_ID_ONBOARD_COMPUTER)
        self.signed = signing_key is not None
        if self.signed:
            s = self.mav.signing
            s.secret_key, s.link_id, s.sign_outgoing = bytes(signing_key), int(link_id) & 0xFF, True
            s.timestamp = max(1, self._clock_ts())
        self._tlog = open(tlog, "ab") if tlog else None
        self.sent = Counter()
        self.errors = 0
        self.skipped = Counter()  # ADSB_VEHICLE not sent: why
        self.clamped = Counter()  # ADSB_VEHICLE fields sent clamped, their valid flag cleared
        self._ids: dict = {}

    def _clock_ts(self) -> int:
        """The clock in signing units (10 us since 2015-01-01); 0 if it gives no finite time."""
        from sitl.mavlink.framing import SIGNING_EPOCH_UNIX_S
        u = float(self._clock())
        return min((1 << 48) - 1, max(0, int((u - SIGNING_EPOCH_UNIX_S) * 1e5))) if math.isfinite(u) else 0

    def write(self, buf: bytes) -> None:
        """pymavlink's MAVLink.send writes the packed frame here."""
        self.sock.sendto(buf, self.addr)

    def _send(self, msg) -> None:
        try:
            if self.signed:
                ts = self._clock_ts()
                if ts > self.mav.signing.timestamp:  # never backwards: +1 per frame, or the clock
                    self.mav.signing.timestamp = ts
            self.mav.send(msg)
            if self._tlog is not None:
                import struct

                from sitl.pacing import (
                    wall_now,  # a tlog stamps wall time (us), by convention
                )
                self._tlog.write(struct.pack(">Q", int(wall_now() * 1e6)) + msg.get_msgbuf())
            self.sent[msg.get_type()] += 1
        except OSError:
            self.errors += 1

    def adsb(self, kind: str, target_id: str, est) -> None:
        """One estimate as ADSB_VEHICLE; never raises (see the class docstring)."""
        try:
            msg = self._adsb_message(kind, target_id, est)
        except Exception as e:  # whatever else an estimate holds: not sent, counted
            self.skipped[f"invalid:{type(e).__name__}"] += 1
            return
        if msg is not None:
            self._send(msg)

    def _adsb_message(self, kind: str, target_id: str, est):
        from pymavlink.dialects.v20 import common as m

        from sitl.geodesy import ecef_to_geodetic
        pos = [float(v) for v in est.pos_ecef_m]
        vel = [float(v) for v in est.vel_ecef_m_s]
        if len(pos) != 3 or len(vel) != 3:
            self.skipped["shape"] += 1
            return None
        if not all(math.isfinite(v) for v in pos):
            self.skipped["non_finite_position"] += 1
            return None
        lat, lon, h = (float(v) for v in ecef_to_geodetic(pos))
        if not (math.isfinite(lat) and math.isfinite(lon) and math.isfinite(h)):
            self.skipped["non_finite_position"] += 1
            return None
        flags = (m.ADSB_FLAGS_VALID_COORDS | m.ADSB_FLAGS_VALID_ALTITUDE | m.ADSB_FLAGS_VALID_HEADING
                 | m.ADSB_FLAGS_VALID_VELOCITY | m.ADSB_FLAGS_VALID_CALLSIGN)
        # ECEF velocity -> NED
        sl, cl, so, co = math.sin(lat), math.cos(lat), math.sin(lon), math.cos(lon)
        vx, vy, vz = vel
        ve = -so * vx + co * vy
        vn = -sl * co * vx - sl * so * vy + cl * vz
        vu = cl * co * vx + cl * so * vy + sl * vz
        if not (math.isfinite(ve) and math.isfinite(vn) and math.isfinite(vu)):
            self.clamped["velocity"] += 1
            flags &= ~(m.ADSB_FLAGS_VALID_VELOCITY | m.ADSB_FLAGS_VALID_HEADING)
            ve = vn = vu = 0.0
        alt_mm = round(h * 1000.0)
        if not -2**31 <= alt_mm < 2**31:  # int32 mm: +-2147 km
            self.clamped["altitude"] += 1
            flags &= ~m.ADSB_FLAGS_VALID_ALTITUDE
            alt_mm = max(-2**31, min(2**31 - 1, alt_mm))
        hor = round(math.hypot(vn, ve) * 100.0)
        ver = round(vu * 100.0)
        if hor > 65535 or not -32768 <= ver <= 32767:  # uint16 / int16 cm/s
            self.clamped["velocity"] += 1
            flags &= ~m.ADSB_FLAGS_VALID_VELOCITY
            hor, ver = min(hor, 65535), max(-32768, min(32767, ver))
        key = (kind, target_id)
        n = self._ids.setdefault(key, len(self._ids))
        icao = (ADSB_ICAO.get(kind, 0xAB0000) + n) & 0xFFFFFFFF
        callsign = f"{kind[:3].upper()}{target_id}".encode("ascii", "replace")[:8]
        heading = (math.degrees(math.atan2(ve, vn)) + 360.0) % 360.0
        emitter = m.ADSB_EMITTER_TYPE_LIGHTER_AIR if kind == "sonde" else m.ADSB_EMITTER_TYPE_UAV
        return self.mav.adsb_vehicle_encode(
            icao, int(round(math.degrees(lat) * 1e7)), int(round(math.degrees(lon) * 1e7)),
            m.ADSB_ALTITUDE_TYPE_GEOMETRIC, int(alt_mm), int(round(heading * 100)) % 36000, int(hor), int(ver),
            callsign, emitter, 1, flags, 0)

    def statustext(self, text: str, severity: int = 4) -> None:
        msg = self.mav.statustext_encode(max(0, min(7, int(severity))), str(text).encode("utf-8", "replace")[:50])
        self._send(msg)

    def close(self) -> None:
        try:
            self.sock.close()
        except OSError:
            pass
        if self._tlog is not None:
            self._tlog.close()
            self._tlog = None


def _from_json(tp, v):
    """A JSON value back to the type ``tp`` a parameter dataclass declares: nested dataclasses
    (also as ``X | None``) rebuilt, lists back to tuples."""
    import dataclasses
    import types
    import typing

    if isinstance(v, dict):
        cands = typing.get_args(tp) if isinstance(tp, types.UnionType) or typing.get_origin(tp) is typing.Union else (tp,)
        for c in cands:
            if dataclasses.is_dataclass(c):
                return _dataclass_from_json(c, v)
        return {k: _from_json(object, x) for k, x in v.items()}
    if isinstance(v, list):
        return tuple(_from_json(object, x) for x in v)
    return v


def _dataclass_from_json(cls, d: dict):
    import typing

    hints = typing.get_type_hints(cls)
    return cls(**{k: _from_json(hints.get(k, object), x) for k, x in d.items()})


def sonde_tracker_from_spec(spec):
    """The sonde tracker's SondeTrackerParams from the spec's ``params`` (None when it has none:
    no sonde). JSON floats round-trip exactly (repr), so they are the composition root's own."""
    from ground_station.sonde import SondeTrackerParams

    d = spec.params.get("sonde_tracker")
    return None if d is None else _dataclass_from_json(SondeTrackerParams, d)


def main(argv=None) -> int:
    from ground_station.node import GroundStationNode, GsConfig
    from sitl.live.worker import WorkerRuntime, open_bus, out_path

    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 1:
        print("usage: python -m ground_station.process SPEC.json", file=sys.stderr)
        return 2
    rt = WorkerRuntime(argv[0])
    spec, scn = rt.spec, rt.scenario
    bus = open_bus(spec, scn.bus.lease_ms)
    gcs = None
    node = None
    try:
        node = GroundStationNode(bus, spec.run_id, GsConfig.from_scenario(scn, sonde_tracker_from_spec(spec)),
                                 incarnation=rt.incarnation)
        if scn.mavlink.enabled:
            try:
                from sitl.mavlink.framing import load_signing_key
                key = load_signing_key(scn.mavlink.signing_key_file) if scn.mavlink.signing_key_file else None
                gcs = GcsLink(scn.mavlink.gcs, out_path(spec, "mav_gs.tlog") if scn.mavlink.tlog else None,
                              signing_key=key)
            except Exception as e:  # no MAVLink: the bus side still runs
                print(f"gs: MAVLink to {scn.mavlink.gcs} not available: {e}", file=sys.stderr)
        if not rt.wait_start():
            return 0
        pacer = rt.pacer()
        hold_sim = scn.ground_station.hold_wall_s * scn.run.speed
        t_end = scn.run.t0_gps_s + scn.run.duration_s
        tick = min(0.1 * scn.run.speed, 1.0 / scn.run.rate_hz)  # ~10 ticks per wall second
        # an epoch is processed once every source publishing (heard within 2.5 epochs) has
        # delivered it, at the latest hold_wall_s after its time (a source that fell silent)
        early_window = 2.5 / scn.run.rate_hz
        t = pacer.sim_now()
        errors = 0
        from collections import deque

        from sitl.pacing import perf_now
        tick_s = deque(maxlen=2000)
        while not rt.stop.is_set():
            if not pacer.wait_until(t):
                break
            w0 = perf_now()
            bus.drain()
            horizon = min(pacer.sim_now(), t_end + hold_sim) - hold_sim
            try:
                out = node.advance(horizon, early_window_s=early_window, now_s=min(pacer.sim_now(), t_end + hold_sim))
            except Exception as e:  # counted, reported, the node keeps running
                errors += 1
                out = []
                if errors <= 10 or errors % 100 == 0:  # the log stays readable
                    print(f"gs: step failed ({errors} so far): {type(e).__name__}: {e}", file=sys.stderr)
            if gcs is not None:
                try:
                    for key, est in out:
                        parts = key.rsplit("/", 2)
                        gcs.adsb(parts[-2], parts[-1], est)
                    for _key, ev in node.events:
                        gcs.statustext(f"integrity {ev.channel}: {ev.event}")
                    for _key, ls in node.link_changes:  # a silent UAV / radar / relay stream, or back
                        gcs.statustext(f"link {ls.link}: {'stale' if ls.stale else 'back'}",
                                       severity=4 if ls.stale else 6)
                except Exception as e:  # the GCS side must not stop the fusion
                    errors += 1
                    if errors <= 10 or errors % 100 == 0:
                        print(f"gs: MAVLink send failed ({errors} so far): {type(e).__name__}: {e}", file=sys.stderr)
            node.events.clear()
            node.link_changes.clear()
            node.link_messages.clear()
            tick_s.append(perf_now() - w0)
            if rt.status_due():
                rt.emit(_status(node, bus, gcs, errors, horizon, tick_s))
            if horizon >= t_end:
                break
            t = max(t + tick, pacer.sim_now())
        bus.drain()
        node.advance(t_end)
        rt.emit({**_status(node, bus, gcs, errors, t_end, tick_s), "event": "done", "gs": node.stats()})
        return 0
    finally:
        if node is not None:
            node.close()
        if gcs is not None:
            gcs.close()
        bus.close()


def _status(node, bus, gcs, errors, t, tick_s=()) -> dict:
    from sitl.pacing import cpu_now
    from sitl.live.worker import bus_counters
    d = {"event": "status", "t_sim_s": t, "cpu_s": cpu_now(), "epochs": node.counters["epochs"], "estimates": node.counters["estimates"],
         "late": node.counters["late"],
         "step_errors": errors + sum(n for k, n in node.counters.items() if k.startswith("step_errors.")),
         **bus_counters(bus),
         "links_stale": sum(lk.stale for lk in node.links.states())}
    for reason in ("future", "stale"):  # the node's time guard: rejected inputs like the bus's
        if node.counters[f"rejected_{reason}"]:
            d["rejected"][f"time:{reason}"] = int(node.counters[f"rejected_{reason}"])
    if gcs is not None:  # skipped / clamped: estimates ADSB_VEHICLE could not carry as they are
        d["mavlink"] = {"sent": dict(gcs.sent), "errors": gcs.errors, "skipped": dict(gcs.skipped),
                        "clamped": dict(gcs.clamped)}
    if tick_s:
        a = sorted(tick_s)
        d["tick_ms"] = {"p50": 1e3 * a[len(a) // 2], "p90": 1e3 * a[int(0.9 * len(a))], "p99": 1e3 * a[min(len(a) - 1, int(0.99 * len(a)))],
                        "max": 1e3 * a[-1]}
    return d


if __name__ == "__main__":
    sys.exit(main())
