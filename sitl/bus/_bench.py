"""Quick measurement of the live bus: 1 publisher process -> embedded router -> 1 subscriber
process, UavNav messages (449 B) through the real codec (encode, decode and validate), or
with ``--raw`` 449 opaque bytes (the transport alone, as the peer figure).

    python -m sitl.bus._bench [--n 20000] [--rate 2000] [--express] [--delivery callback]
                              [--raw]

Throughput: the publisher sends ``--n`` messages as fast as it can; msgs/s at the receiver
between its first and last delivery. Latency: once the receiver has taken all of those, the
publisher sends ``--n-lat`` messages paced at ``--rate`` msgs/s, each stamped (in ``t_gps_s``, for this benchmark only) with
CLOCK_MONOTONIC, which every process on the machine shares; the receiver takes the
difference in its callback, after decoding. Reports one JSON line. A wall-clock tool, not
a simulation component.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

_SUB = r"""
import json, sys, time
import numpy as np
from sitl.bus import ZenohTransport
import struct
ep, delivery, n_thr, n_lat, raw = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), sys.argv[5] == "1"
bus = ZenohTransport(connect=[ep], delivery=delivery)
phase = {"thr": [], "lat": []}
def cb(key, msg):
    now = time.monotonic()
    phase[key.split("/")[1]].append((now, now - msg.t_gps_s))
def cb_raw(key, payload):
    now = time.monotonic()
    phase[key.split("/")[1]].append((now, now - struct.unpack_from("<d", payload)[0]))
if raw:
    bus.subscribe_raw("bench/**", cb_raw)
else:
    bus.subscribe("bench/**", cb)
print("ready", flush=True)
deadline = time.monotonic() + 120
told = False
while (len(phase["thr"]) < n_thr or len(phase["lat"]) < n_lat) and time.monotonic() < deadline:
    if delivery == "queue":
        if not bus.drain():
            time.sleep(0.0002)
    else:
        time.sleep(0.001)
    if not told and len(phase["thr"]) >= n_thr:
        print("thr-done", flush=True)  # the latency phase starts on an idle receiver
        told = True
thr = phase["thr"]
lat = np.array([d for _, d in phase["lat"]]) * 1e3
out = {"received_thr": len(thr), "received_lat": len(phase["lat"]),
       "msgs_per_s": (len(thr) - 1) / (thr[-1][0] - thr[0][0]) if len(thr) > 1 else None,
       "lat_ms_p50": float(np.percentile(lat, 50)) if lat.size else None,
       "lat_ms_p99": float(np.percentile(lat, 99)) if lat.size else None,
       "lat_ms_max": float(lat.max()) if lat.size else None,
       "rejected": dict(bus.stats.total.rejected)}
bus.close()
print(json.dumps(out), flush=True)
"""

_PUB = r"""
import sys, time
import numpy as np
from sitl.bus import UavNav, ZenohTransport
import struct
ep, n_thr, n_lat, rate, express, raw = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4]), sys.argv[5] == "1", sys.argv[6] == "1"
bus = ZenohTransport(connect=[ep], express=express)
cov = np.eye(6)
def nav(seq, t):
    return UavNav(t_gps_s=t, source_id="uav-1", seq=seq, pos_ecef_m=[4.2e6, 1.1e6, 4.6e6],
                  vel_ecef_m_s=[10.0, -2.0, 0.5], cov=cov, n_sats=9, fix_type=3)
if raw:  # the transport alone: 449 opaque bytes, no message built, encoded or decoded
    pad = bytes(441)
    class _Raw:
        def publish(self, key, t):
            bus.publish_raw(key, struct.pack("<d", t) + pad)
    pub = _Raw()
    def send(key, seq):
        pub.publish(key, time.monotonic())
else:
    def send(key, seq):
        bus.publish(key, nav(seq, time.monotonic()))
assert bus.wait_for_subscribers("bench/thr/uav/1/nav", 10)
assert bus.wait_for_subscribers("bench/lat/uav/1/nav", 10)
for i in range(n_thr):
    send("bench/thr/uav/1/nav", i)
sys.stdin.readline()  # the receiver has taken the throughput phase
time.sleep(0.2)
period = 1.0 / rate
t_next = time.monotonic()
for i in range(n_lat):
    t_next += period
    while time.monotonic() < t_next:
        pass  # paced by spinning: sleep() is too coarse at kHz rates
    send("bench/lat/uav/1/nav", i)
sys.stdin.readline()  # stay open until the receiver has everything
bus.close()
"""


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m sitl.bus._bench")
    ap.add_argument("--n", type=int, default=20000, help="messages for throughput")
    ap.add_argument("--n-lat", type=int, default=4000, help="messages for latency")
    ap.add_argument("--rate", type=float, default=2000.0, help="latency phase msgs/s")
    ap.add_argument("--express", action="store_true")
    ap.add_argument("--delivery", choices=("callback", "queue"), default="callback")
    ap.add_argument("--raw", action="store_true",
                    help="the transport alone: opaque bytes, no codec (the peer figure)")
    a = ap.parse_args(argv)
    from .router import Router

    from sitl.runtime import child_env
    env = child_env()  # the peers import this copy of the packages
    with Router() as r:
        ep = r.endpoints[0]
        sub = subprocess.Popen([sys.executable, "-c", _SUB, ep, a.delivery, str(a.n),
                                str(a.n_lat), "1" if a.raw else "0"], stdout=subprocess.PIPE, text=True, env=env)
        assert sub.stdout.readline().strip() == "ready"
        pub = subprocess.Popen([sys.executable, "-c", _PUB, ep, str(a.n), str(a.n_lat),
                                str(a.rate), "1" if a.express else "0", "1" if a.raw else "0"],
                               stdin=subprocess.PIPE, text=True, env=env)
        try:
            line = sub.stdout.readline()
            if line.strip() == "thr-done":
                pub.stdin.write("\n")
                pub.stdin.flush()
                line = sub.stdout.readline()
            res = json.loads(line)
        finally:
            pub.communicate("\n", timeout=30)
            sub.wait(timeout=30)
    res.update(n=a.n, n_lat=a.n_lat, rate=a.rate, express=a.express, delivery=a.delivery, raw=a.raw,
               load=os.getloadavg()[0])
    print(json.dumps(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
