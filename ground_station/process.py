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
    """ADSB_VEHICLE and STATUSTEXT to the ground-control endpoint (UDP, pymavlink)."""

    def __init__(self, gcs: str, tlog=None):
        from pymavlink import mavutil

        host, port = gcs.rsplit(":", 1)
        self.conn = mavutil.mavlink_connection(f"udpout:{host}:{int(port)}", source_system=GS_SYSID,
                                               source_component=191, dialect="common")
        self.mav = self.conn.mav
        self._tlog = open(tlog, "ab") if tlog else None
        self._mav_tlog = self.mav
        self.sent = Counter()
        self.errors = 0
        self._ids: dict = {}

    def _send(self, msg) -> None:
        try:
            self.mav.send(msg)
            if self._tlog is not None:
                import struct

                from sitl.live.pacer import (
                    wall_now,  # a tlog stamps wall time (us), by convention
                )
                self._tlog.write(struct.pack(">Q", int(wall_now() * 1e6)) + msg.get_msgbuf())
            self.sent[msg.get_type()] += 1
        except OSError:
            self.errors += 1

    def adsb(self, kind: str, target_id: str, est) -> None:
        from pymavlink.dialects.v20 import common as m

        from sitl.geodesy import ecef_to_geodetic
        lat, lon, h = (float(v) for v in ecef_to_geodetic(est.pos_ecef_m))
        # ECEF velocity -> NED
        sl, cl, so, co = math.sin(lat), math.cos(lat), math.sin(lon), math.cos(lon)
        vx, vy, vz = (float(v) for v in est.vel_ecef_m_s)
        ve = -so * vx + co * vy
        vn = -sl * co * vx - sl * so * vy + cl * vz
        vu = cl * co * vx + cl * so * vy + sl * vz
        key = (kind, target_id)
        n = self._ids.setdefault(key, len(self._ids))
        icao = ADSB_ICAO.get(kind, 0xAB0000) + n
        callsign = f"{kind[:3].upper()}{target_id}"[:8].encode()
        heading = (math.degrees(math.atan2(ve, vn)) + 360.0) % 360.0
        flags = (m.ADSB_FLAGS_VALID_COORDS | m.ADSB_FLAGS_VALID_ALTITUDE | m.ADSB_FLAGS_VALID_HEADING
                 | m.ADSB_FLAGS_VALID_VELOCITY | m.ADSB_FLAGS_VALID_CALLSIGN)
        emitter = m.ADSB_EMITTER_TYPE_LIGHTER_AIR if kind == "sonde" else m.ADSB_EMITTER_TYPE_UAV
        msg = self.mav.adsb_vehicle_encode(
            icao, int(round(math.degrees(lat) * 1e7)), int(round(math.degrees(lon) * 1e7)),
            m.ADSB_ALTITUDE_TYPE_GEOMETRIC, int(round(h * 1000)), int(round(heading * 100)) % 36000,
            max(0, min(65535, int(round(math.hypot(vn, ve) * 100)))), max(-32768, min(32767, int(round(vu * 100)))),
            callsign, emitter, 1, flags, 0)
        self._send(msg)

    def statustext(self, text: str, severity: int = 4) -> None:
        msg = self.mav.statustext_encode(severity, text[:50].encode())
        self._send(msg)

    def close(self) -> None:
        try:
            self.conn.close()
        except OSError:
            pass
        if self._tlog is not None:
            self._tlog.close()


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
        node = GroundStationNode(bus, spec.run_id, GsConfig.from_scenario(scn))
        if scn.mavlink.enabled:
            try:
                gcs = GcsLink(scn.mavlink.gcs, out_path(spec, "mav_gs.tlog") if scn.mavlink.tlog else None)
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

        from sitl.live.pacer import perf_now
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
    from sitl.live.pacer import cpu_now
    from sitl.live.worker import bus_counters
    d = {"event": "status", "t_sim_s": t, "cpu_s": cpu_now(), "epochs": node.counters["epochs"], "estimates": node.counters["estimates"],
         "late": node.counters["late"], "step_errors": errors, **bus_counters(bus),
         "links_stale": sum(lk.stale for lk in node.links.states())}
    if gcs is not None:
        d["mavlink"] = {"sent": dict(gcs.sent), "errors": gcs.errors}
    if tick_s:
        a = sorted(tick_s)
        d["tick_ms"] = {"p50": 1e3 * a[len(a) // 2], "p90": 1e3 * a[int(0.9 * len(a))], "p99": 1e3 * a[min(len(a) - 1, int(0.99 * len(a)))],
                        "max": 1e3 * a[-1]}
    return d


if __name__ == "__main__":
    sys.exit(main())
