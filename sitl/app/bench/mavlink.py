"""`skyfuse bench mavlink`: the vehicles' MAVLink output, CPU per endpoint per step.

N UAV endpoints (``--uavs``) stepped at 10 Hz of simulated time over real loopback UDP
(vehicles/mavlink/bench.py: the streams at their default rates to a sink socket), measured
twice in the same run, interleaved (``--rounds`` pairs): the group's batched streams (the
frames of a step framed together, each endpoint's packed into few datagrams:
vehicles/mavlink/endpoint/batch.py) and the peer, pymavlink's own path (one ``<message>_send``
per frame, a datagram each). The headline is the median ratio batched / pymavlink of the process
CPU time per endpoint-step; the share of one core N endpoints need at 10 Hz and the datagrams
sent are printed beside. A benchmark, not a test: it reads the process clock.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from sitl.app.args import OUTPUT_FILE
from sitl.app.provenance import options_scenario, write_json
from sitl.params import add_flags, integer, number, optional, param, validate


@dataclass(frozen=True)
class MavlinkBenchOptions:
    """`skyfuse bench mavlink`'s options, declared once (sitl.params)."""

    uavs: int = param(200, check=integer(lo=1, hi=249), doc="UAV endpoints in the group (MAVLink system ids end at 249)")
    duration: float = param(5.0, check=number(0, lo_open=True, hi=3600), metavar="S",
                            doc="simulated seconds per measurement (10 steps per second)")
    rounds: int = param(3, check=integer(lo=1, hi=50), doc="interleaved pairs (batched, pymavlink)")
    json: Path | None = param(None, check=optional(OUTPUT_FILE), metavar="FILE", doc="also write the result as JSON")

    __post_init__ = validate


def add_args(p) -> None:
    add_flags(p, MavlinkBenchOptions)


def run(opts: MavlinkBenchOptions) -> dict:
    from vehicles.mavlink.bench import bench_group

    bench_group(4, 1.0)  # the framing kernel loaded (or compiled) before anything is timed
    pairs = []
    for _ in range(opts.rounds):
        per_frame = bench_group(opts.uavs, opts.duration, batch_streams=False)
        batched = bench_group(opts.uavs, opts.duration, batch_streams=True)
        pairs.append({"pymavlink": per_frame, "batched": batched,
                      "ratio": batched["cpu_us_per_endpoint_step"] / per_frame["cpu_us_per_endpoint_step"]})
    ratios = sorted(p["ratio"] for p in pairs)
    return {"uavs": opts.uavs, "duration_s": opts.duration, "pairs": pairs,
            "median_ratio_batched_to_pymavlink": ratios[len(ratios) // 2], "load_avg": os.getloadavg()}


def main(args) -> int:
    from sitl.app.args import options_of

    opts = options_of(MavlinkBenchOptions, args)
    res = run(opts)
    for k, p in enumerate(res["pairs"], 1):
        a, b = p["pymavlink"], p["batched"]
        print(f"pair {k}: pymavlink {a['cpu_us_per_endpoint_step']:.1f} us per endpoint-step ({a['datagrams_sent']} "
              f"datagrams), batched {b['cpu_us_per_endpoint_step']:.1f} us ({b['datagrams_sent']} datagrams), "
              f"ratio {p['ratio']:.3f}")
    best = res["pairs"][0]["batched"]
    print(f"{opts.uavs} endpoints at 10 Hz: batched / pymavlink CPU median {res['median_ratio_batched_to_pymavlink']:.3f} "
          f"over {opts.rounds} pairs; {best['packets_per_endpoint_s']:.1f} frames per endpoint-s; load "
          f"{res['load_avg'][0]:.1f}")
    if opts.json is not None:
        write_json(opts.json, res, scenario=options_scenario(opts))
    return 0
