"""The ground-station worker of a live run: ``python -m ground_station.process SPEC.json``.

A `GroundStationNode` (the batch beacon locator and sonde tracker) on the run's Zenoh bus,
stepped by the paced clock: every tick it takes in what has arrived and processes the epochs
that are complete (every source publishing has delivered them) or older than
``ground_station.hold_wall_s`` (x speed, in simulated time), publishing the
Estimates on ``<run>/gs/estimate/**``. It is also a MAVLink 2 component toward the
ground-control endpoint (ground_station.mavlink_link.GcsLink: system 250, HEARTBEAT at 1 Hz of
the paced simulation time -- MAV_STATE_STANDBY at 1 Hz wall before the run starts --, signed like the vehicles when ``[mavlink] signing_key_file`` is set,
with its signing state in ``OUT/mav_signing_250.json``; with several MAVLink blocks, all of
this to every block's GCS address, sitl.mavlink.blocks): the beacon and sonde estimates as
ADSB_VEHICLE with their 1-sigma uncertainty in UTM_GLOBAL_POSITION, the integrity events its
trackers publish (``<run>/gs/integrity/**``) and its input links turning stale or coming back
(``<run>/gs/link/**``, "link uav2: stale") as rate-limited STATUSTEXT; ``mav_gs.tlog`` records them.

Journal (ground_station.journal): every input payload the node's subscriptions take in, raw and
in their order, and every ``advance()`` with its arguments go to ``OUT/gs_journal.log``
(``gs_journal.r<N>.log`` for incarnation N), each tick's records to the kernel before the tick
publishes anything, so `skyfuse replay` reproduces this process's decisions exactly. The status
line's ``journal`` block: its records, bytes and the main loop's time spent writing it.
A restart (incarnation > 0) first resumes its node from the earlier incarnations' journals
(ground_station.journal.resume; one stderr line with the counts and the time it took).
"""
from __future__ import annotations

import os
import sys

from ground_station.mavlink_link import ADSB_ICAO, GS_SYSID, GcsLink  # noqa: F401  (the GCS link's home before)


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
    journal = None
    try:
        if scn.mavlink.enabled:
            try:
                from sitl.mavlink.blocks import MavlinkPlan
                from sitl.mavlink.framing import load_signing_key
                key = load_signing_key(scn.mavlink.signing_key_file) if scn.mavlink.signing_key_file else None
                plan = MavlinkPlan.of(scn)  # system 250 on every MAVLink block (sitl.mavlink.blocks)
                blocks = range(1, plan.n_blocks + 1)
                gcs = GcsLink([f"{h}:{p}" for h, p in plan.gcs_addrs()],
                              out_path(spec, "mav_gs.tlog") if scn.mavlink.tlog else None,
                              signing_key=key, link_id=[plan.link_id(k) for k in blocks],
                              signing_state=([out_path(spec, plan.signing_state_name(k, GS_SYSID)) for k in blocks]
                                             if key is not None else None))
            except Exception as e:  # no MAVLink: the bus side still runs
                print(f"gs: MAVLink to {scn.mavlink.gcs} not available: {e}", file=sys.stderr)
        # the link first: it heartbeats (standby) while the node is built and the run waits to start
        standby = _standby_heartbeats(gcs) if gcs is not None else None
        try:
            from ground_station.journal import (RESUME_KEY, JournalingTransport, config_to_json, open_journal, resume,
                                                resume_sources)
            from ground_station.node import GroundStationNode, GsConfig  # numba kernels: seconds on a cold start
            from sitl.pacing import perf_now
            config = GsConfig.from_scenario(scn, sonde_tracker_from_spec(spec))
            # the journal: what the node consumed and when, for an exact replay (ground_station.journal)
            # a restart resumes from the earlier incarnations' journals (ground_station.journal.resume)
            earlier = resume_sources(spec.out_dir, rt.incarnation, spec.run_id) if rt.incarnation > 0 else []
            try:
                journal = open_journal(spec.out_dir, rt.incarnation,
                                       {"run_id": spec.run_id, "worker": spec.name, "config": config_to_json(config),
                                        RESUME_KEY: earlier},
                                       t_s=scn.run.t0_gps_s, clock=perf_now)
                node_bus = JournalingTransport(bus, journal)
            except (OSError, ValueError) as e:  # the fusion runs anyway; a replay then re-derives its decisions
                print(f"gs: no journal (replay will not be exact): {type(e).__name__}: {e}", file=sys.stderr)
                journal, node_bus = _NoJournal(), bus
            node = GroundStationNode(node_bus, spec.run_id, config, incarnation=rt.incarnation)
            if earlier:
                w0 = perf_now()
                done = resume(node, [os.path.join(spec.out_dir, n) for n in earlier])
                print(f"gs: incarnation {rt.incarnation} resumed from {', '.join(earlier)}: {done} "
                      f"in {perf_now() - w0:.2f} s", file=sys.stderr)
            if not rt.wait_start():
                return 0
        finally:
            if standby is not None:
                standby()
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
            if gcs is not None:  # HEARTBEAT when due (simulation time) before the step, which may take long
                gcs.tick(pacer.sim_now())
            journal.t_s = pacer.sim_now()  # what this drain takes in arrived by then
            bus.drain()
            now = min(pacer.sim_now(), t_end + hold_sim)
            horizon = now - hold_sim
            journal.advance(horizon, early_window, now)  # journaled (to the kernel) before any output
            try:
                out = node.advance(horizon, early_window_s=early_window, now_s=now)
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
                        gcs.integrity_event(ev)
                    for _key, ls in node.link_changes:  # a silent UAV / radar / relay stream, or back
                        gcs.link_change(ls)
                except Exception as e:  # the GCS side must not stop the fusion
                    errors += 1
                    if errors <= 10 or errors % 100 == 0:
                        print(f"gs: MAVLink send failed ({errors} so far): {type(e).__name__}: {e}", file=sys.stderr)
            node.events.clear()
            node.link_changes.clear()
            node.link_messages.clear()
            tick_s.append(perf_now() - w0)
            if rt.status_due():
                rt.emit(_status(node, bus, gcs, errors, horizon, tick_s, journal))
            if horizon >= t_end:
                break
            t = max(t + tick, pacer.sim_now())
        journal.t_s = pacer.sim_now()
        bus.drain()
        journal.advance(t_end, None, None)
        try:
            node.advance(t_end)
        except Exception as e:
            errors += 1
            print(f"gs: last step failed: {type(e).__name__}: {e}", file=sys.stderr)
        rt.emit({**_status(node, bus, gcs, errors, t_end, tick_s, journal), "event": "done", "gs": node.stats()})
        return 0
    finally:
        if node is not None:
            node.close()
        if journal is not None:
            journal.close()
        if gcs is not None:
            gcs.close()
        bus.close()


class _NoJournal:
    """Stands in for the journal when it cannot be written (the status line says so)."""

    t_s = 0.0

    def advance(self, *_):
        pass

    def status(self) -> dict:
        return {"path": None}

    def close(self):
        pass


def _standby_heartbeats(gcs, period_wall_s: float = 1.0):
    """HEARTBEAT (MAV_STATE_STANDBY) once per wall second while the worker waits for the start
    command -- the launcher waits for every worker, which may be compiling kernels for a minute:
    the GCS sees the ground station at once, not when the run starts.  No simulated clock runs
    yet, so this one is paced by the wall clock.  Returns the stop function; it joins the
    thread, so the link is the main loop's alone afterwards (pymavlink's sequence numbers and
    signing state are not shared between threads)."""
    import threading

    from pymavlink.dialects.v20 import common as m
    done = threading.Event()

    def run():
        while True:
            gcs.heartbeat(m.MAV_STATE_STANDBY)
            if done.wait(period_wall_s):
                return

    th = threading.Thread(target=run, name="gs-standby-heartbeat", daemon=True)
    th.start()

    def stop():
        done.set()
        th.join(5.0)
    return stop


def _status(node, bus, gcs, errors, t, tick_s=(), journal=None) -> dict:
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
    if gcs is not None:  # skipped / clamped: what the MAVLink messages could not carry as it is
        d["mavlink"] = gcs.status()
    if journal is not None:  # its records, bytes and the time the main loop spent writing it
        d["journal"] = journal.status()
    if tick_s:
        a = sorted(tick_s)
        d["tick_ms"] = {"p50": 1e3 * a[len(a) // 2], "p90": 1e3 * a[int(0.9 * len(a))], "p99": 1e3 * a[min(len(a) - 1, int(0.99 * len(a)))],
                        "max": 1e3 * a[-1]}
    return d


if __name__ == "__main__":
    sys.exit(main())
