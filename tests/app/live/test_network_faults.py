"""Network faults in a live run (issue 8, loopback only, bounded): the launcher's MAVLink
front and per-vehicle proxies, the control key and `skyfuse fault set` / `list`, and a short
multi-process run whose ground-station Zenoh link is partitioned and recovers by itself."""
from __future__ import annotations

import json
import socket
import threading
import time

import numpy as np
import pytest
from tests.procs import dead as _dead
from tests.procs import tcp_free as _tcp_free
from tests.procs import udp_base as _base_port
from tests.procs import udp_free as _udp_free

from sitl.scenario import parse_scenario


def _threads(prefix: str) -> list[str]:
    return [t.name for t in threading.enumerate() if t.name.startswith(prefix) and t.is_alive()]


# ------------------------------------------------------------------ MAVLink: front + proxies


@pytest.mark.live
def test_mavlink_front_takes_each_vehicle_through_its_own_proxy_both_ways():
    """Three vehicle endpoints (pymavlink, sysids 1-3, sending from base_port + 10 i to the
    front: what the vehicle workers' specs name as their GCS) and a GCS peer. Vehicle 2's
    uplink loses 30 %: the GCS receives exactly what the proxy's LinkTruth delivered, per
    vehicle, and the proxy's MAVLink tap counts the loss from the sequence numbers; the GCS's
    replies reach the right vehicle, from the front's address; a datagram from an address
    that is no vehicle is dropped and counted; closing frees every port and thread."""
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    from sitl.app.live_faults import LiveFaults
    gcs = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    gcs.bind(("127.0.0.1", 0))
    gcs.settimeout(0.05)
    base = _base_port(3)
    scn = parse_scenario(f"""
[mavlink]
gcs = "127.0.0.1:{gcs.getsockname()[1]}"
base_port = {base}
[sonde]
enabled = false
[faults]
"mav:2:up" = "loss=30%"
""")
    lf = LiveFaults(scn, ["tcp/127.0.0.1:7447"])  # TCP proxies only connect when a client comes
    lf.start(0.0)
    vehicles = []
    try:
        front = tuple(lf.front.addr)
        assert lf.overrides["vehicles0"]["mavlink_gcs"] == f"{front[0]}:{front[1]}"
        assert "mavlink_gcs" not in lf.overrides["gs"]
        assert sorted(lf.links()) == sorted([f"mav:{i}:{d}" for i in (1, 2, 3) for d in ("up", "down")]
                                            + ["zenoh:vehicles0", "zenoh:gs"])
        for i in range(3):
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            s.bind(("127.0.0.1", base + 10 * i))
            s.settimeout(0.05)
            vehicles.append((s, mavlink.MAVLink(None, srcSystem=i + 1, srcComponent=1)))
        n = 200
        rx = mavlink.MAVLink(None)
        seen: dict[int, list[int]] = {1: [], 2: [], 3: []}
        upstream = {}
        quiet = threading.Event()

        def gcs_reader():  # the GCS reads while the vehicles send (its socket buffer is finite)
            idle_since = time.monotonic()
            while time.monotonic() - idle_since < 1.0:
                try:
                    data, addr = gcs.recvfrom(4096)
                except TimeoutError:
                    continue
                idle_since = time.monotonic()
                for m in rx.parse_buffer(data) or []:
                    seen[m.get_srcSystem()].append(m.get_seq())
                    upstream[m.get_srcSystem()] = addr
            quiet.set()
        reader = threading.Thread(target=gcs_reader)
        reader.start()
        for _ in range(n):
            for s, mav in vehicles:
                s.sendto(mav.heartbeat_encode(2, 3, 0, 0, 4).pack(mav), front)
                mav.seq = (mav.seq + 1) % 256  # what MAVLink.send does after packing
            time.sleep(0.001)  # paced: a loopback UDP buffer must not overflow before the proxies read it
        stranger = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        stranger.bind(("127.0.0.1", 0))
        stranger.sendto(b"\xfd\x00junk", front)
        stranger.close()
        reader.join(10.0)
        assert quiet.is_set()
        truth2 = lf.udp[2].stats().up
        assert truth2.truth.sent == n and truth2.truth.dropped_loss > 0
        assert [len(seen[1]), len(seen[2]), len(seen[3])] == [n, truth2.truth.delivered, n]
        kept = np.setdiff1d(np.arange(n), truth2.truth.dropped_indices())
        assert seen[2] == [int(k) % 256 for k in kept]  # exactly the packets the truth delivered
        view = truth2.truth.receiver_view()
        assert (truth2.tap.seq.missing, truth2.tap.seq.duplicates) == (view["missing"], 0)
        assert lf.udp[1].stats().up.truth.dropped == 0
        # each vehicle has its own upstream address at the GCS; a reply reaches that vehicle only
        assert len(set(upstream.values())) == 3
        gmav = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
        gcs.sendto(gmav.heartbeat_encode(6, 8, 0, 0, 4).pack(gmav), upstream[3])
        got = {}
        deadline = time.monotonic() + 3.0
        while time.monotonic() < deadline and 2 not in got:
            for i, (s, _) in enumerate(vehicles):
                try:
                    _data, addr = s.recvfrom(4096)
                    got[i] = addr
                except TimeoutError:
                    pass
        assert list(got) == [2] and tuple(got[2]) == front
        assert lf.front.counters["unknown_source"] == 1
        # a run-time change through the board (what a `fault set mav:3 loss=100%` does): both directions
        assert lf.board.set("mav:3", "loss=100%") == "loss=100%"
        s3, mav3 = vehicles[2]
        for _ in range(20):
            s3.sendto(mav3.heartbeat_encode(2, 3, 0, 0, 4).pack(mav3), front)
            mav3.seq = (mav3.seq + 1) % 256
        deadline = time.monotonic() + 2.0
        while time.monotonic() < deadline and lf.udp[3].stats().up.received < n + 20:
            time.sleep(0.01)
        st3 = lf.udp[3].stats()
        assert st3.up.received == n + 20 and st3.up.forwarded == n and st3.up.truth.dropped_loss == 20
        assert lf.udp[3].stats().down.truth.sent == 1  # the reply before the change
        rep = lf.report()
        assert [h["spec"] for h in rep["links"]["mav:3:down"]["history"]] == ["none", "loss=100%"]
        assert rep["links"]["mav:2:up"]["current"] == "loss=30%"
        assert rep["links"]["mav:2:up"]["truth"]["truth"]["dropped_loss"] == truth2.truth.dropped_loss
        ports = [p.addr[1] for p in lf.udp.values()] + [front[1]]
        tports = [p.addr[1] for p in lf.tcp.values()]
    finally:
        lf.close()
        for s, _ in vehicles:
            s.close()
        gcs.close()
    assert all(_udp_free(p) for p in ports) and all(_tcp_free(p) for p in tports)
    assert not _threads("netfault-proxies")


# ------------------------------------------------------------------ control key and the CLI


@pytest.fixture
def control_server(tmp_path):
    """A launcher's control side without workers: an embedded router, a FaultBoard with two
    fake links, served on the bus (drained by a thread as the launcher's loop does), and an
    OUT/run.json naming them."""
    from sitl.bus import Router, ZenohTransport
    from sitl.app.launcher import _RunJson
    from sitl.netfault.control import FaultBoard, serve
    applied = []
    clock = [12.5]
    board = FaultBoard(lambda: clock[0])
    for name in ("mav:1:up", "mav:1:down", "zenoh:gs"):
        board.add_link(name, lambda spec, t, name=name: applied.append((name, spec.to_text(), t)))
    router = Router(listen=["tcp/127.0.0.1:0"])
    bus = ZenohTransport(connect=router.endpoints)
    lines = []
    serve(board, bus, "ctl", on_line=lines.append)
    rj = _RunJson(tmp_path / "run.json", "ctl", router.endpoints, board)
    rj.write()
    board.on_change = rj.write
    stop = threading.Event()

    def pump():
        while not stop.is_set():
            bus.drain()
            stop.wait(0.02)
    th = threading.Thread(target=pump, daemon=True)
    th.start()
    yield {"board": board, "applied": applied, "out": tmp_path, "lines": lines, "router": router, "rj": rj}
    stop.set()
    th.join(2.0)
    bus.close()
    router.close()


@pytest.mark.live
def test_fault_set_is_applied_acknowledged_and_listed(control_server, capsys):
    from sitl.netfault import parse_spec
    from sitl.app.fault_cli import main
    cs = control_server
    out = str(cs["out"])
    canon = parse_spec("loss=10% delay=100ms~20ms").to_text()
    assert main(["set", "mav:1", "loss=10%", "delay=100ms~20ms", "--out", out]) == 0
    assert capsys.readouterr().out.strip() == f"mav:1 = {canon}"
    # both directions of mav:1, once each (the CLI may repeat a request: applied once), at the board's clock
    assert cs["applied"] == [("mav:1:up", canon, 12.5), ("mav:1:down", canon, 12.5)]
    assert main(["set", "zenoh:gs", "none", "--zenoh", cs["router"].endpoints[0], "--run", "ctl"]) == 0
    assert cs["applied"][-1] == ("zenoh:gs", parse_spec("none").to_text(), 12.5)
    assert main(["set", "bus:ctl/uav/2/**", "loss=20%", "--out", out]) == 0  # the workers apply it
    doc = json.loads((cs["out"] / "run.json").read_text())
    assert doc["faults"]["mav:1:up"] == canon and doc["faults"]["bus:ctl/uav/2/**"] == "loss=20%"
    capsys.readouterr()
    assert main(["list", "--out", out]) == 0
    listed = dict(line.split(None, 1) for line in capsys.readouterr().out.strip().splitlines())
    assert listed == {"mav:1:up": canon, "mav:1:down": canon, "zenoh:gs": "none", "bus:ctl/uav/2/**": "loss=20%"}
    hist = cs["board"].report()["links"]["mav:1:up"]["history"]
    assert [h["by"] for h in hist] == ["control"] and hist[0]["t_s"] == 12.5


@pytest.mark.live
@pytest.mark.parametrize("argv, expect", [
    (["set", "mav:1", "loss=120%"], "loss=120%"),          # bad spec: refused here, nothing sent
    (["set", "mav:7", "loss=1%"], "unknown link 'mav:7'"),  # not in run.json's links
    (["set", "zenoh:nobody", "delay=1s"], "zenoh:gs"),      # not a link name at all
])
def test_fault_set_refuses_bad_input_with_exit_2_and_one_line(control_server, capsys, argv, expect):
    from sitl.app.fault_cli import main
    cs = control_server
    assert main(argv + ["--out", str(cs["out"])]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and err.startswith("error: ") and expect in err, err
    assert cs["applied"] == []


@pytest.mark.live
def test_launcher_refuses_and_counts_what_it_cannot_apply_and_goes_on(control_server, capsys):
    """Requests that pass the CLI's checks but not the launcher's (a link missing from this
    run, a TCP link given packet loss): exit 2 with the launcher's one-line reason, counted;
    a good request afterwards still works. No launcher at all: exit 1 after the timeout."""
    from sitl.app.fault_cli import main
    cs = control_server
    ep = cs["router"].endpoints[0]
    assert main(["set", "mav:7", "loss=1%", "--zenoh", ep, "--run", "ctl"]) == 2
    assert "unknown link 'mav:7'" in capsys.readouterr().err
    assert main(["set", "zenoh:gs", "loss=5%", "--out", str(cs["out"])]) == 2  # refused here: a TCP link
    assert "TCP stream" in capsys.readouterr().err
    cs["board"].links["zenoh:gs"].apply = lambda spec, t: (_ for _ in ()).throw(
        ValueError("zenoh:gs: the proxy refused it"))  # a refusal only the launcher's side can see
    assert main(["set", "zenoh:gs", "delay=5ms", "--out", str(cs["out"])]) == 2
    assert "the proxy refused it" in capsys.readouterr().err
    assert cs["board"].bad == {"unknown link": 1, "bad spec": 1}
    assert any("refused" in line for line in cs["lines"])
    assert main(["set", "mav:1:up", "duplicate=1%", "--out", str(cs["out"])]) == 0
    assert main(["set", "mav:1", "loss=1%", "--zenoh", ep, "--run", "nobody-here", "--timeout", "1"]) == 1
    cs["rj"].write(finished=True)
    t0 = time.monotonic()
    assert main(["set", "mav:1", "loss=1%", "--out", str(cs["out"])]) == 1  # run.json: finished
    assert time.monotonic() - t0 < 1.0


@pytest.mark.live
def test_a_run_without_faults_refuses_changes_and_loads_no_fault_models(tmp_path, capsys):
    """A launcher whose scenario has no [faults] answers every change with one line (exit 2),
    counts it, and its control side does not import sitl.netfault (numpy/scipy models)."""
    import subprocess
    import sys

    from sitl.bus import Router, ZenohTransport
    from sitl.bus.faultctl import NoFaultBoard, serve
    from sitl.app.fault_cli import main
    code = ("import sys, sitl.app.launcher, sitl.app.live_faults; "
            "sys.exit(any(m.startswith('sitl.netfault') for m in sys.modules))")
    assert subprocess.run([sys.executable, "-c", code], timeout=60, check=False).returncode == 0
    board = NoFaultBoard()
    with Router(listen=["tcp/127.0.0.1:0"]) as router, ZenohTransport(connect=router.endpoints) as bus:
        serve(board, bus, "plain")
        stop = threading.Event()
        th = threading.Thread(target=lambda: [bus.drain() or stop.wait(0.02) for _ in iter(stop.is_set, True)])
        th.start()
        try:
            ep = router.endpoints[0]
            assert main(["set", "bus:plain/uav/**", "loss=5%", "--zenoh", ep, "--run", "plain"]) == 2
            assert main(["list", "--zenoh", ep, "--run", "plain"]) == 0
        finally:
            stop.set()
            th.join(2.0)
    err = capsys.readouterr().err
    assert "no [faults] table" in err and len(err.strip().splitlines()) == 1
    assert board.report()["bad_requests"] == {"no faults in this run": 1}


@pytest.mark.live
def test_worker_applies_each_bus_request_once_and_counts_bad_ones():
    """A worker's side of the control key (subscribe_async: no drain): a bus rule is applied
    once however often the CLI repeats the request; a bad key expression or spec is counted,
    other links are left to the launcher; the truths are summed per rule."""
    from sitl.bus import Router, ZenohTransport
    from sitl.bus.schema import FaultControl
    from sitl.netfault import KeyFaults
    from sitl.netfault.control import WorkerFaultControl, control_key
    kf = KeyFaults([("w/uav/**", "none")], seed=3)
    with Router(listen=["tcp/127.0.0.1:0"]) as router, \
            ZenohTransport(connect=router.endpoints, faults=[kf]) as wbus, \
            ZenohTransport(connect=router.endpoints) as cli:
        ctl = WorkerFaultControl(wbus, "w", kf)
        wbus.subscribe_async(control_key("w"), ctl.on_control)
        assert cli.wait_for_subscribers(control_key("w"), 5.0)
        reqs = [("bus:w/uav/2/**", "loss=100%", 1), ("bus:w/uav/2/**", "loss=100%", 1),  # a repeat
                ("bus:w/**/*", "loss=1%", 2), ("bus:w/x", "loss=120%", 3), ("mav:1", "loss=1%", 4)]
        for link, spec, seq in reqs:
            cli.publish(control_key("w"), FaultControl(t_gps_s=0.0, source_id="cli", seq=seq, link=link, spec=spec))
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline and ctl.applied + sum(ctl.bad.values()) < 3:
            time.sleep(0.01)
        time.sleep(0.1)  # the repeat and the mav request would have been handled by now too
        assert ctl.applied == 1 and sum(ctl.bad.values()) == 2
        for i in range(10):
            for u in (1, 2):
                wbus.publish(f"w/uav/{u}/nav", nav_msg(i))
        assert [e for e, _ in kf.rules] == ["w/uav/2/**", "w/uav/**"]  # a new rule goes first
        tr = ctl.truths()
        assert tr["bus:w/uav/2/**"]["dropped_loss"] == tr["bus:w/uav/2/**"]["sent"] == 10
        assert tr["bus:w/uav/**"]["delivered"] == tr["bus:w/uav/**"]["sent"] == 10


def nav_msg(i):
    from tests.sitl.bus.test_bus import nav
    return nav(seq=i, t_gps_s=1.0 + i)


# ------------------------------------------------------------------ a short live run


@pytest.mark.slow
@pytest.mark.live
def test_live_run_gs_partition_recovers_without_restart_and_fault_set_changes_a_link(tmp_path):
    """3 UAVs, no MAVLink, x10, 44 s simulated, lease 500 ms; the GS's Zenoh link is silently
    partitioned from 18 to 30 s (1.2 wall s: its session is lost) and a bus rule drops
    a UAV's beacon measurements. While it runs `fault set` delays the vehicles' link and a bad
    request is refused. The run completes, the GS is never restarted and reconnects by itself
    (a second connection through its proxy), estimates resume after the partition, the
    report's faults block holds the history and the truths, nothing is left behind."""
    from sitl.app.launcher import launch
    from sitl.app.fault_cli import main as fault_main
    speed = 10.0
    scn = parse_scenario(f"""
[run]
id = "nfl"
duration_s = 44.0
speed = {speed}
[bus]
lease_ms = 500
log = false
[mavlink]
enabled = false
[sonde]
enabled = false
[ground_station]
hold_wall_s = 0.3
[faults]
"zenoh:gs" = "partition=18-30"
"bus:nfl/uav/2/beacon/**" = "loss=25%"
"mav:1" = "loss=5%"
""")
    seen = {}

    def on_started(sup):
        seen["pids"] = [c.pid for c in sup.children.values()]
        seen["proxy_ports"] = [p.addr[1] for p in sup.live_faults.tcp.values()]

        def control():
            time.sleep(0.5)  # into the run (~4 simulated s)
            seen["set"] = fault_main(["set", "zenoh:vehicles0", "delay=20ms", "--out", str(tmp_path)])
            seen["set_bus"] = fault_main(["set", "bus:nfl/uav/3/nav", "loss=100%", "--out", str(tmp_path)])
            seen["bad"] = fault_main(["set", "mav:1", "loss=1%", "--out", str(tmp_path)])
        th = threading.Thread(target=control)
        th.start()
        seen["thread"] = th

    report = launch(scn, tmp_path, quiet=True, on_started=on_started, warm_up=False)
    seen["thread"].join(10.0)
    assert report["ok"], report.get("error")
    assert report["restarts"] == 0 and not report["orphans"]
    assert seen["set"] == 0 and seen["set_bus"] == 0 and seen["bad"] == 2
    f = report["faults"]["links"]
    gs = f["zenoh:gs"]["truth"]
    assert gs["partitions"] == 1 and gs["accepted"] >= 2, gs  # the session was lost and came back
    hist = f["zenoh:vehicles0"]["history"]
    assert [h["by"] for h in hist] == ["scenario", "control"] and hist[1]["spec"] == "delay=20ms"
    assert 2.0 < hist[1]["t_s"] < 40.0, hist
    assert f["zenoh:vehicles0"]["truth"]["truth_up"]["delay_s_max"] == pytest.approx(0.02)
    bus_rule = f["bus:nfl/uav/2/beacon/**"]["truth"]
    assert bus_rule["sent"] > 0 and bus_rule["dropped_loss"] > 0
    assert bus_rule["sent"] == bus_rule["delivered"] + bus_rule["dropped"]
    # a bus rule added at run time by the control key reached the publishing worker
    added = f["bus:nfl/uav/3/nav"]
    assert [h["by"] for h in added["history"]] == ["control"]
    assert added["truth"]["sent"] > 0 and added["truth"]["dropped_loss"] == added["truth"]["sent"]
    assert report["faults"]["requests"] == 2
    # ... and is in the workers' spec files, ahead of the scenario's rule: a restarted worker has it
    from sitl.scenario import WorkerSpec
    respec = WorkerSpec.read(tmp_path / "specs" / "vehicles0.json").scenario_obj().faults.of_kind("bus")
    assert respec == [("bus:nfl/uav/3/nav", "loss=100%"), ("bus:nfl/uav/2/beacon/**", "loss=25%")]
    # the GS's estimates: some before the partition, none published while it lasted reach
    # the launcher, and they resume after it heals
    pts = report["error_series"]["beacon/b1"]
    ts = [t for t, _ in pts]
    assert any(t < 18 for t in ts) and any(t > 32 for t in ts), ts
    after = [e for t, e in pts if t > 34]
    assert after and max(after) < 200.0, after
    assert report["faults"]["bad_requests"] == {}  # mav:1: refused by the CLI (not in run.json's links)
    assert report["faults"]["inactive"] == ["mav:1"]  # MAVLink is off: said, not silently dropped
    for pid in seen["pids"]:
        assert _dead(pid)
    assert all(_tcp_free(p) for p in seen["proxy_ports"])
    assert not _threads("netfault-proxies")
    doc = json.loads((tmp_path / "run.json").read_text())
    assert doc["finished"] and "zenoh:gs" in doc["links"]


def test_board_refuses_a_bus_rule_that_matches_no_key_of_the_run():
    """A run-time bus rule that can match none of the run's keys (e.g. `uav2` for the key chunk
    `2`) is refused with one line naming it, as the scenario check refuses it at load; a rule that
    matches is applied; without the run's keys nothing is checked."""
    from sitl.netfault.control import FaultBoard
    from sitl.scenario import parse_scenario, run_keys

    keys = run_keys(parse_scenario('[run]\nid = "r"\n'))
    assert "r/uav/2/nav" in keys and "r/radar/arls1/sonde/s0000" in keys
    board = FaultBoard(bus_keys=keys)
    with pytest.raises(ValueError) as e:
        board.set("bus:*/uav/uav2/**", "loss=1%")
    assert "matches no key" in str(e.value) and "\n" not in str(e.value) and "r/uav/1/nav" in str(e.value)
    assert board.bus_order == []
    assert board.set("bus:*/uav/2/**", "loss=1%") == "loss=1%" and board.bus_order == ["bus:*/uav/2/**"]
    assert FaultBoard().set("bus:*/uav/uav2/**", "loss=1%") == "loss=1%"
