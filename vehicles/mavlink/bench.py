"""CPU cost of an EndpointGroup: ``python -m vehicles.mavlink.bench [N] [SECONDS] [STREAM_HZ]``.

Steps N UAV endpoints at 10 Hz of simulated time over real loopback UDP (the streams go to a
sink socket nobody reads: the kernel drops what overflows, as a GCS that is not there) and
reports the process CPU time per endpoint per step, and the share of one core that N
endpoints at 10 Hz need: three interleaved pairs of the group's batched streams (batch.py) and
pymavlink's frame-per-datagram path, and their median ratio.  STREAM_HZ (optional) sets every position stream to that rate (as
MAVProxy's REQUEST_DATA_STREAM does); default: the endpoint's default rates.
A benchmark, not a test: it reads the process clock.
"""
from __future__ import annotations

import math
import socket
import sys
import time

from .endpoint import STREAMS, EndpointGroup, VehicleEndpoint
from .params import ParamStore, ParamSpec
from .telemetry import VehicleTelemetry


def bench_group(n: int = 200, sim_seconds: float = 20.0, step_hz: float = 10.0, stream_hz: float | None = None,
                t0_gps_s: float = 1_400_000_000.0, batch_streams: bool = True) -> dict:
    sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sink.bind(("127.0.0.1", 0))
    rates = None if stream_hz is None else {k: (1.0 if k == 0 else stream_hz) for k in STREAMS}
    specs = [ParamSpec(f"P{i}", float(i)) for i in range(8)]
    eps = [VehicleEndpoint(i + 1, "uav", gcs=sink.getsockname(), listen=("127.0.0.1", 0),
                           params=ParamStore(specs), stream_rates_hz=rates) for i in range(n)]
    tels = [VehicleTelemetry(math.radians(45 + 1e-3 * i), math.radians(30), 3000.0, (100.0, 0.0, 0.0),
                             satellites_visible=9, hdop=0.9, eph_m=2.0) for i in range(n)]
    steps = int(round(sim_seconds * step_hz))
    try:
        with EndpointGroup(eps, batch_streams=batch_streams) as g:
            cpu0, wall0 = time.process_time(), time.perf_counter()
            for k in range(steps):
                g.step(t0_gps_s + k / step_hz, tels)
            cpu, wall = time.process_time() - cpu0, time.perf_counter() - wall0
            sent = g.counters["sent"]
            datagrams = g.counters["tx_datagrams"]
    finally:
        sink.close()
    per_step_us = cpu / (steps * n) * 1e6
    peer_us = _pymavlink_floor_us(sent)
    return {"endpoints": n, "steps": steps, "step_hz": step_hz, "cpu_s": cpu, "wall_s": wall,
            "batch_streams": bool(batch_streams), "cpu_us_per_endpoint_step": per_step_us, "packets_sent": sent,
            "datagrams_sent": datagrams,
            "packets_per_endpoint_s": sent / (n * sim_seconds),
            "core_share_at_rate": per_step_us * 1e-6 * n * step_hz,
            "max_endpoints_one_core": int(1.0 / (per_step_us * 1e-6 * step_hz)),
            "pymavlink_send_us_per_packet": peer_us,
            "ratio_to_pymavlink_floor": cpu / (sent * peer_us * 1e-6)}


def _pymavlink_floor_us(n_packets: int) -> float:
    """The peer: CPU us per packet of bare pymavlink (encode + pack + sendto, one socket),
    measured now, so that the group's cost is also read as a ratio on a shared machine."""
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sink.bind(("127.0.0.1", 0))
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    addr = sink.getsockname()

    class _File:
        def write(self, buf):
            tx.sendto(buf, addr)

    mav = mavlink.MAVLink(_File(), srcSystem=1, srcComponent=1)
    n = max(1000, min(int(n_packets), 50_000))
    try:
        cpu0 = time.process_time()
        for k in range(n):
            mav.attitude_send(k, 0.1, 0.2, 0.3, 0.0, 0.0, 0.0)
        return (time.process_time() - cpu0) / n * 1e6
    finally:
        sink.close()
        tx.close()


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    try:
        n = int(argv[0]) if argv else 200
        secs = float(argv[1]) if len(argv) > 1 else 20.0
        hz = float(argv[2]) if len(argv) > 2 else None
    except ValueError:
        print("usage: python -m vehicles.mavlink.bench [N] [SIM_SECONDS] [STREAM_HZ]", file=sys.stderr)
        return 2
    # the batched streams against pymavlink's frame-per-datagram path, interleaved in this run
    bench_group(4, 1.0)  # the framing kernel loaded (or compiled) before anything is timed
    ratios = []
    for _ in range(3):
        pair = [bench_group(n, secs, stream_hz=hz, batch_streams=b) for b in (False, True)]
        for r in pair:
            print(" ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in r.items()))
        ratios.append(pair[1]["cpu_us_per_endpoint_step"] / pair[0]["cpu_us_per_endpoint_step"])
    print(f"batched / per-frame CPU per endpoint-step: median {sorted(ratios)[1]:.3f} "
          f"(pairs: {', '.join(f'{x:.3f}' for x in ratios)})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
