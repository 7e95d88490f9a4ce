"""The MAVLink blocks' plan (sitl.mavlink.blocks): which vehicle gets which (block, system id),
each block's GCS port and each vehicle's ports, and the scenario's checks of it.

References are the convention's own statement, written out by hand here (not the code's
formulas): ArduPilot SITL's instance layout 5760 + 10 N for block 1, the GCS ports 14550, 14560,
... of the issue, and the ports counted one by one for 1,000 UAVs."""
from __future__ import annotations

import pytest

from sitl.mavlink.blocks import MavlinkPlan
from sitl.scenario import ScenarioError, default_scenario


def test_block_1_is_todays_single_network():
    p = MavlinkPlan(n_vehicles=4)
    assert p.n_blocks == 1
    assert [(p.block_of(i), p.sysid_of(i), p.listen_port(i)) for i in range(4)] == [
        (1, 1, 5760), (1, 2, 5770), (1, 3, 5780), (1, 4, 5790)]
    assert p.gcs_addrs() == [("127.0.0.1", 14550)]
    assert p.signing_state_name(1, 3) == "mav_signing_3.json" and p.link_id(1) == 0


def test_260_uavs_and_a_sonde_in_two_blocks():
    p = MavlinkPlan(n_vehicles=261)
    assert p.n_blocks == 2
    # vehicle 249 is the last of block 1; vehicle 250 is system id 1 of block 2
    assert (p.block_of(248), p.sysid_of(248), p.listen_port(248)) == (1, 249, 5760 + 2480)
    assert (p.block_of(249), p.sysid_of(249), p.listen_port(249)) == (2, 1, 5761)
    assert (p.block_of(260), p.sysid_of(260), p.listen_port(260)) == (2, 12, 5761 + 110)
    assert list(p.indices(2)) == list(range(249, 261))
    assert p.gcs_addrs() == [("127.0.0.1", 14550), ("127.0.0.1", 14560)]
    assert p.link_id(2) == 1 and p.signing_state_name(2, 250) == "mav_signing_b2_250.json"
    assert p.describe(259) == "vehicle 260 (block 2, system id 11)"


def test_1000_uavs_ports_are_distinct_and_clear_of_the_gcs_ports_and_the_ephemeral_range():
    p = MavlinkPlan(n_vehicles=1001)  # 1,000 UAVs and the sonde
    assert p.n_blocks == 5  # 4 x 249 = 996 < 1001
    ports = [p.listen_port(i) for i in range(1001)]
    assert len(set(ports)) == 1001
    assert min(ports) == 5760 and max(ports) <= 5760 + 2490  # one block's span, whatever the swarm
    gcs = [port for _, port in p.gcs_addrs()]
    assert gcs == [14550, 14560, 14570, 14580, 14590]
    assert not set(gcs) & set(ports) and max(ports) < 32768
    # every (block, sysid) once, sysids 1..249 (the GS's 250 and the GCS's 255 never taken)
    pairs = {(p.block_of(i), p.sysid_of(i)) for i in range(1001)}
    assert len(pairs) == 1001 and max(s for _, s in pairs) == 249
    # the port tells the vehicle back
    assert all(p.vehicle_at_port(port) == i for i, port in enumerate(ports))
    assert p.vehicle_at_port(5759) is None and p.vehicle_at_port(14550) is None
    assert p.problems() == []


def test_block_size_and_gcs_step():
    p = MavlinkPlan(n_vehicles=7, block_size=3, gcs_port=20000, gcs_port_step=2, base_port=6000)
    assert p.n_blocks == 3
    assert [(p.block_of(i), p.sysid_of(i)) for i in range(7)] == [(1, 1), (1, 2), (1, 3), (2, 1), (2, 2), (2, 3),
                                                                  (3, 1)]
    assert [p.listen_port(i) for i in range(7)] == [6000, 6010, 6020, 6001, 6011, 6021, 6002]
    assert [port for _, port in p.gcs_addrs()] == [20000, 20002, 20004]
    assert MavlinkPlan(n_vehicles=7, block_size=3, gcs_port_step=0).gcs_addrs() == [("127.0.0.1", 14550)] * 3


def _scn(**sections):
    """The default scenario with some keys changed, parsed and validated as a file would be."""
    from sitl.scenario import scenario_from_dict, to_toml_like
    d = to_toml_like(default_scenario().to_dict())
    for name, changes in sections.items():
        d.setdefault(name, {}).update(changes)
    return scenario_from_dict(d, "test")


@pytest.mark.parametrize("uavs, mavlink, key, text", [
    (2490, {}, "uavs.count", "at most 10 x mavlink.block_size = 2490"),  # + the sonde: 2491
    (30, {"block_size": 3}, "uavs.count", "at most 10 x mavlink.block_size = 30"),
    (300, {"base_port": 64000}, "mavlink.base_port", "<= 65535"),
    (300, {"gcs": "127.0.0.1:65530"}, "mavlink.gcs", "<= 65535"),
    # block 2's GCS port 5770 is UAV 2's port
    (300, {"gcs": "127.0.0.1:5760", "base_port": 5770}, "mavlink.gcs", "block 2's GCS port 5770"),
    (300, {"gcs": "127.0.0.1:5761", "base_port": 5760, "gcs_port_step": 9}, "mavlink.gcs", "block 1's GCS port 5761"),
    (300, {"block_size": 0}, "mavlink.block_size", ""),
    (300, {"block_size": 250}, "mavlink.block_size", ""),
    (300, {"gcs_port_step": -1}, "mavlink.gcs_port_step", ""),
])
def test_scenario_rejects_a_plan_that_cannot_work_in_one_line(uavs, mavlink, key, text):
    with pytest.raises(ScenarioError) as e:
        _scn(uavs={"count": uavs}, mavlink=mavlink)
    msg = str(e.value)
    assert msg.startswith(f"scenario: {key}: ") and text in msg and "\n" not in msg


def test_scenario_takes_1000_uavs_with_mavlink_and_a_remote_gcs_on_any_port():
    scn = _scn(uavs={"count": 1000})
    assert MavlinkPlan.of(scn).n_blocks == 5 and scn.mavlink.block_size == 249
    # a GCS on another host may use a port number a local vehicle has
    _scn(uavs={"count": 300}, mavlink={"gcs": "10.1.2.3:5770"})


def test_scenario_rejects_the_router_on_a_vehicle_tcp_port():
    with pytest.raises(ScenarioError, match=r"^scenario: bus.listen: .*vehicle 2 \(block 1, system id 2\)"):
        _scn(bus={"listen": "tcp/127.0.0.1:5770"})
    _scn(bus={"listen": "tcp/127.0.0.1:5770"}, mavlink={"tcp": False})  # UDP only: fine


def test_fault_override_sends_every_block_to_the_front():
    from sitl.scenario import worker_specs
    scn = _scn(uavs={"count": 300, "per_process": 200})
    specs = worker_specs(scn, ["tcp/127.0.0.1:1"], "/tmp/x", {"vehicles1": {"mavlink_gcs": "127.0.0.1:40001"}})
    obj = {s.name: s.scenario_obj() for s in specs}
    assert MavlinkPlan.of(obj["vehicles1"]).gcs_addrs() == [("127.0.0.1", 40001)] * 2
    assert MavlinkPlan.of(obj["vehicles0"]).gcs_addrs() == [("127.0.0.1", 14550), ("127.0.0.1", 14560)]


def test_fault_link_names_take_vehicle_numbers_beyond_249():
    from sitl.netfault.spec import LinkNameError, canonical_link
    assert canonical_link("mav:260:up") == "mav:260:up"
    with pytest.raises(LinkNameError):
        canonical_link("mav:2491")
    scn = _scn(uavs={"count": 300}, faults={"mav:300": "loss=1%"})
    assert scn.faults.get("mav:300")
    with pytest.raises(ScenarioError, match="vehicle number in 1..301"):
        _scn(uavs={"count": 300}, faults={"mav:302": "loss=1%"})


def test_start_text_is_a_line_per_block_not_per_vehicle():
    from pathlib import Path

    from sitl.app.launcher import start_text
    text = start_text(_scn(uavs={"count": 1000}), Path("o"))
    lines = text.splitlines()
    assert len(lines) == 2 + 5
    assert "block 2: vehicles 250-498 as system ids 1-249 -> 127.0.0.1:14560: `mavproxy.py --master " \
           "udpin:127.0.0.1:14560`" in text
    assert "block 5: vehicles 997-1001 (the last is the sonde) as system ids 1-5 -> 127.0.0.1:14590" in text
    assert "udpout/tcp 127.0.0.1:5764 + 10 (s - 1) (..5804)" in text
