"""The vehicle group's columnar publishing (vehicles.process.VehicleGroup, sitl.bus.UavGroupEpoch)
against the per-UAV path it replaces -- the reference: the same messages, bytes and order, and the
same ground-station estimates -- and the worker's MAVLink input served between the slices of a
world step (EndpointGroup.serve_input)."""
from __future__ import annotations

import time

import numpy as np
import pytest

from sitl.bus import BusRecorder, InMemoryTransport, read_bus_log_records
from sitl.scenario import default_scenario
from tests.procs import udp_base
from vehicles.process import VehicleGroup, _InputService


def _log(tmp_path, name, scn, n_uavs, epochs, **kw):
    """[(key, payload)] of a group's epochs as the bus recorder logs them, and the transport's
    publication count."""
    bus = InMemoryTransport(start_t_gps_s=scn.run.t0_gps_s)
    path = tmp_path / f"{name}.log"
    rec = BusRecorder(bus, path, key_expr=f"{scn.run.id}/**", append=False)
    seen = []
    bus.subscribe(f"{scn.run.id}/uavs/*/epoch", lambda k, m: seen.append(k))
    g = VehicleGroup(scn, list(range(n_uavs)), bus, np.random.SeedSequence([scn.run.seed, 1000]), **kw)
    for k in range(epochs):
        t = scn.run.t0_gps_s + k / scn.run.rate_hz
        g.step(t)
        bus.drain(t)
    rec.close()
    published = bus.stats.published
    bus.close()
    return [(r.key, r.payload) for r in read_bus_log_records(path)], published, seen, g


def test_columnar_epochs_log_the_per_uav_messages_bit_for_bit(tmp_path):
    # 130 UAVs: two group messages per epoch (UAV_GROUP_MAX 100); the sonde and the beacon's truth as ever
    scn = default_scenario().replace(uavs={"count": 130, "radius_m": 20000.0}, mavlink={"enabled": False})
    ref, n_ref, seen_ref, g_ref = _log(tmp_path, "per_uav", scn, 130, 6, columnar=False)
    got, n_got, seen, g = _log(tmp_path, "columnar", scn, 130, 6, columnar=True)
    assert not seen_ref and len(seen) == 12 and set(seen) == {f"{scn.run.id}/uavs/uavs1-100/epoch",
                                                              f"{scn.run.id}/uavs/uavs101-130/epoch"}
    assert len(got) == len(ref) > 6 * 130 and got == ref  # keys, payloads and order
    kinds = {k.split("/")[1] for k, _ in ref}
    assert kinds == {"uav", "truth", "sonde", "radar"}
    # one payload per 100 UAVs per epoch instead of up to three per UAV
    assert n_got == n_ref - sum(1 for k, _ in ref if k.split("/")[1] == "uav" or "/truth/uav/" in k) + 12
    assert g.links_nonpositive == g_ref.links_nonpositive and g.sent == n_got


def test_a_transport_with_fault_filters_gets_per_uav_messages():
    """Bus faults are per key (a rule on uav/2/beacon/** must see UAV 2's own messages)."""
    scn = default_scenario().replace(mavlink={"enabled": False}, sonde={"enabled": False})
    keys = []
    bus = InMemoryTransport(faults=[lambda key, p, t: (keys.append(key), [(t, p)])[1]])
    g = VehicleGroup(scn, [0, 1, 2], bus, np.random.SeedSequence(1))
    assert not g.publishes_columnar
    g.step(scn.run.t0_gps_s)
    assert keys and not any("/uavs/" in k for k in keys) and any(k.endswith("/uav/2/beacon/b1") for k in keys)
    assert VehicleGroup(scn, [0, 1, 2], InMemoryTransport(), np.random.SeedSequence(1)).publishes_columnar


@pytest.mark.slow
def test_ground_station_estimates_are_the_same_from_columnar_epochs():
    from ground_station.node import GroundStationNode
    from sitl.app.components import gs_config

    scn = default_scenario().replace(run={"duration_s": 40.0}, mavlink={"enabled": False})

    def run(columnar):
        bus = InMemoryTransport(start_t_gps_s=scn.run.t0_gps_s)
        node = GroundStationNode(bus, scn.run.id, gs_config(scn))
        est = []
        bus.subscribe(f"{scn.run.id}/gs/estimate/**", lambda k, m: est.append((k, m.t_gps_s, m.pos_ecef_m.tobytes(),
                                                                              m.cov.tobytes())))
        g = VehicleGroup(scn, list(range(scn.uavs.count)), bus, np.random.SeedSequence([scn.run.seed, 1000]),
                         columnar=columnar)
        for k in range(int(scn.run.duration_s * scn.run.rate_hz) + 1):
            t = scn.run.t0_gps_s + k / scn.run.rate_hz
            g.step(t)
            bus.drain(t)
            node.advance(t)
            bus.drain(t)
        stats = node.stats()
        node.close()
        bus.close()
        return est, stats, node.bus.group_epochs

    ref, s_ref, n_ref = run(False)
    got, s_got, n_got = run(True)
    assert n_ref == 0 and n_got > 30
    kinds = {k.split("/")[-2] for k, *_ in ref}
    assert kinds == {"beacon", "sonde"} and len(ref) > 40
    assert got == ref  # every estimate, bit for bit
    assert s_got["links"] == s_ref["links"] and s_got["node"] == s_ref["node"]


def test_a_world_step_calls_between_after_the_flight_and_before_the_sonde():
    scn = default_scenario().replace(mavlink={"enabled": False})
    calls = []
    g = VehicleGroup(scn, [0, 1, 2], InMemoryTransport(), np.random.SeedSequence(1))
    g.step(scn.run.t0_gps_s, between=lambda: calls.append((g.epoch, g.last_nav is not None)))
    assert calls == [(0, False), (0, True)]  # before the sensors, then between the UAVs and the sonde
    no_sonde = VehicleGroup(scn, [0, 1, 2], InMemoryTransport(), np.random.SeedSequence(1), with_sonde=False)
    calls.clear()
    no_sonde.step(scn.run.t0_gps_s, between=lambda: calls.append(1))
    assert calls == [1]


@pytest.mark.live
def test_serve_input_answers_a_command_at_once_and_sends_no_stream():
    from pymavlink import mavutil

    from vehicles.process import build_endpoints

    base = udp_base(3)
    gcs = mavutil.mavlink_connection("udpin:127.0.0.1:0", source_system=255)
    scn = default_scenario().replace(mavlink={"gcs": f"127.0.0.1:{gcs.port.getsockname()[1]}", "base_port": base,
                                              "tlog": False}, sonde={"enabled": False})
    g = VehicleGroup(scn, [0, 1, 2], InMemoryTransport(), np.random.SeedSequence(1), with_sonde=False)
    eps = build_endpoints(g, scn, "unused")
    cli = mavutil.mavlink_connection(f"udpout:127.0.0.1:{base + 10}", source_system=255)
    try:
        t0 = scn.run.t0_gps_s
        g.step(t0)
        serve = _InputService(eps, budget_s=0.05, timer=time.perf_counter)
        serve()  # before a tick: nothing
        serve.start_tick(t0)
        cli.mav.command_long_send(2, 1, mavutil.mavlink.MAV_CMD_REQUEST_MESSAGE, 0,
                                  mavutil.mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION, 0, 0, 0, 0, 0, 0)
        got = []
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline and not any(m.get_type() == "COMMAND_ACK" for m in got):
            serve()
            m = cli.recv_match(blocking=True, timeout=0.05)
            while m is not None:
                got.append(m)
                m = cli.recv_match(blocking=False)
        types = [m.get_type() for m in got]
        assert "COMMAND_ACK" in types, types
        ack = next(m for m in got if m.get_type() == "COMMAND_ACK")
        assert ack.command == mavutil.mavlink.MAV_CMD_REQUEST_MESSAGE and ack.get_srcSystem() == 2
        assert "HEARTBEAT" not in types  # the streams go out in the endpoints' own step only
        assert serve.failed == [] and 0.0 <= serve.remaining_s() <= 0.05 and serve.used_s > 0
    finally:
        eps.close()
        for c in (gcs, cli):
            c.close()
