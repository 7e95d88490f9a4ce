"""A scenario in batch mode: the live run's components (vehicles.process.VehicleGroup,
ground_station.node.GroundStationNode) stepped in one process in simulation time over an
InMemoryTransport -- deterministic for a seed, as fast as the machine goes. The reference the
live run is compared with (the same scenario and seed give the same statistics).

The composition root imports the components statically (function-level: a light import)."""
from __future__ import annotations

import math

import numpy as np

from sitl.app.scoring import ErrorTracker


def run_batch(scn, *, settle_s: float = 0.0, progress=None, record=None) -> dict:
    """record: a path: the run's bus traffic goes to a bus log there (as a live run's)."""
    from sitl.bus import InMemoryTransport

    from ground_station import node as gn
    from sitl.app.components import gs_config
    run = scn.run
    # [faults]: the bus rules act on the in-memory bus as the workers' publisher filters do live
    # (same models, times since the run's start, deterministic for the seed); the MAVLink and Zenoh
    # links are live sockets, absent in batch mode (listed, not applied)
    links = list(scn.faults.links) if scn.faults else []
    rules = [(name[4:], spec) for name, spec in links if name.startswith("bus:")]
    mf = None
    if rules:
        from sitl.app.experiments.common import MeasurementFaults
        mf = MeasurementFaults(rules, ["**"], seed=int(run.seed), t0_gps_s=run.t0_gps_s)
    bus = InMemoryTransport(start_t_gps_s=run.t0_gps_s, faults=[mf] if mf is not None else ())
    scorer = ErrorTracker(keep_s=1e9, settle_s=settle_s, t0_gps_s=run.t0_gps_s, clock=lambda: bus.now_s,
                          max_ahead_s=scn.ground_station.max_ahead_s)
    scorer.subscribe(bus, run.id)
    recorder = None
    if record is not None:
        from sitl.bus.buslog import BusRecorder
        recorder = BusRecorder(bus, record, key_expr=f"{run.id}/**", append=False, clock=lambda: bus.now_s)
    node = gn.GroundStationNode(bus, run.id, gs_config(scn))
    groups = vehicle_groups(scn, bus)
    dt = 1.0 / run.rate_hz
    K = int(math.floor(run.duration_s * run.rate_hz + 1e-9)) + 1
    for k in range(K):
        t = run.t0_gps_s + k * dt
        for g in groups:
            g.step(t)
        bus.drain(t)
        node.advance(t)
        bus.drain(t)
        if progress and k % 100 == 0:
            progress("[batch]", done=k * dt, total=run.duration_s)
    out = {"errors": scorer.summary(), "gs": node.stats(), "published": bus.stats.published,
           "series": {f"{a}/{b}": v for (a, b), v in scorer.series.items()}}
    if links:
        out["faults"] = {"bus_rules": [f"bus:{e} = {spec}" for e, spec in rules],
                         "not_in_batch": [name for name, _ in links if not name.startswith("bus:")],
                         "injected": mf.totals() if mf is not None else {}}
    node.close()
    if recorder is not None:
        out["recorded"] = recorder.records
        recorder.close()
    bus.close()
    return out


def vehicle_groups(scn, bus) -> list:
    """The scenario's vehicle groups as the live workers build them (uavs.per_process UAVs each;
    the first also the beacon's truth and the sonde; seeds SeedSequence([run.seed, 1000 + g]))."""
    from vehicles import process as vp
    groups = []
    per = scn.uavs.per_process
    for g in range(scn.n_uav_processes):
        idx = list(range(g * per, min(scn.uavs.count, (g + 1) * per)))
        groups.append(vp.VehicleGroup(scn, idx, bus, np.random.SeedSequence([scn.run.seed, 1000 + g]),
                                      with_beacon_truth=g == 0, with_sonde=g == 0 and scn.sonde.enabled))
    return groups


def warm_up(scn, epochs: int = 5) -> None:
    """Step the scenario's components for a few epochs (batch), so that every compiled kernel
    they use is in numba's on-disk cache before the live workers start (a kernel compiled
    in the middle of a live run stalls that worker for seconds)."""
    d = scn.to_dict()
    short = scn.replace(run={"duration_s": max(1.0, (epochs - 1) / scn.run.rate_hz)},
                        uavs={"count": min(scn.uavs.count, 3) if scn.uavs.count else 0,
                              "per_process": 100,
                              "starts": tuple(tuple(s) for s in scn.uavs.start_points()[:3]) if d["uavs"]["starts"]
                              else ()})
    run_batch(short)
    if scn.mavlink.enabled:  # the live workers' MAVLink stream framing (a batch run has no endpoints)
        from vehicles.mavlink.endpoint import batch as mav_batch
        mav_batch.warm()


def main(argv=None) -> int:
    """``python -m sitl.app.batch SCENARIO.json --warm-up``: warm the compiled kernels."""
    import json
    import sys

    from sitl.scenario import to_toml_like, scenario_from_dict
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 2 or argv[1] != "--warm-up":
        print("usage: python -m sitl.app.batch SCENARIO.json --warm-up", file=sys.stderr)
        return 2
    with open(argv[0], encoding="utf-8") as f:
        scn = scenario_from_dict(to_toml_like(json.load(f)), argv[0])
    warm_up(scn)
    return 0


if __name__ == "__main__":
    import sys
    sys.exit(main())
