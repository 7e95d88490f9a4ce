"""The live plumbing without the full demo: pacer, worker runtime, supervisor (restart and
clean shutdown with dummy workers: no orphans, ports freed), replay against batch."""
from __future__ import annotations

import dataclasses
import io
import json
import os
import signal
import socket
import sys
import textwrap
import threading
import time

import pytest
from tests.procs import dead as _dead
from tests.procs import tcp_free as _tcp_free
from tests.procs import udp_base

from sitl.pacing import Pacer
from sitl.app.supervisor import Supervisor

# ------------------------------------------------------------------ pacer


class FakeClock:
    def __init__(self, t=1000.0):
        self.t = t

    def __call__(self):
        return self.t


class FakeStop(threading.Event):
    """A stop event whose wait advances the fake clock instead of sleeping."""

    def __init__(self, clock):
        super().__init__()
        self.clock = clock
        self.waited = 0.0

    def wait(self, timeout=None):
        self.clock.t += timeout
        self.waited += timeout
        return self.is_set()


def test_pacer_maps_sim_to_wall_at_speed():
    clk = FakeClock()
    p = Pacer(4.0, 500.0, wall_start_s=1000.0, clock=clk)
    assert p.sim_now() == 500.0
    clk.t = 1002.5
    assert p.sim_now() == pytest.approx(510.0)
    assert p.wall_at(520.0) == pytest.approx(1005.0)
    with pytest.raises(ValueError):
        Pacer(0.0, 0.0)


def test_pacer_epochs_wait_for_their_time():
    clk = FakeClock()
    stop = FakeStop(clk)
    p = Pacer(2.0, 0.0, wall_start_s=1000.0, clock=clk, stop=stop)
    seen = []
    for t in p.epochs(0.0, 1.0, 5.0):
        seen.append((t, clk.t))
    assert [t for t, _ in seen] == [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]
    for t, wall in seen:  # never early, never later than the wait granularity
        assert p.wall_at(t) <= wall + 1e-9
    assert stop.waited == pytest.approx(2.5)
    assert p.late_epochs == 0 and p.skipped_epochs == 0


def test_pacer_skips_when_far_behind_and_stops_on_request():
    clk = FakeClock()
    stop = FakeStop(clk)
    p = Pacer(1.0, 0.0, wall_start_s=1000.0, clock=clk, stop=stop)
    out = []
    for t in p.epochs(0.0, 1.0, 100.0, max_lag_s=3.0):
        out.append(t)
        if t == 2.0:
            clk.t += 10.0  # a 10 s stall after epoch 2
        if t >= 20.0:
            stop.set()
    # epoch 2 came at sim 2 s; after the stall it is sim 12 s: epochs 3..11 are skipped and
    # the latest due one, 12, comes next
    assert out[:4] == [0.0, 1.0, 2.0, 12.0]
    assert p.skipped_epochs == 9
    assert out[-1] == 20.0


# ------------------------------------------------------------------ worker runtime


def _spec(tmp_path, **kw):
    from sitl.scenario import default_scenario, worker_specs
    spec = worker_specs(default_scenario(), [], tmp_path)[0]
    for k, v in kw.items():
        setattr(spec, k, v)
    return spec.write(tmp_path / "spec.json")


def test_worker_runtime_protocol(tmp_path):
    from sitl.live.worker import WorkerRuntime
    r_in, w_in = os.pipe()
    out = io.StringIO()
    rt = WorkerRuntime(_spec(tmp_path), out=out, stdin=os.fdopen(r_in), install_signals=False)
    w = os.fdopen(w_in, "w")
    w.write("garbage\n" + json.dumps({"cmd": "start", "wall_start_s": 1234.5}) + "\n")
    w.flush()
    assert rt.wait_start(timeout_s=5.0)
    assert rt.wall_start_s == 1234.5 and sum(rt.bad_commands.values()) == 1
    assert json.loads(out.getvalue().splitlines()[0])["event"] == "ready"
    assert not rt.stop.is_set()
    w.close()  # the launcher is gone: the worker stops by itself
    assert rt.stop.wait(5.0)


# ------------------------------------------------------------------ supervisor

DUMMY = textwrap.dedent("""
    import json, os, signal, socket, subprocess, sys, time
    mode, marks, port = sys.argv[1], sys.argv[2], int(sys.argv[3])
    if mode == "stubborn":
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
    first = not os.path.exists(os.path.join(marks, "ran-" + mode))
    open(os.path.join(marks, "ran-" + mode), "a").close()
    gc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])
    srv = socket.socket(); srv.bind(("127.0.0.1", port)); srv.listen()
    with open(os.path.join(marks, "pids"), "a") as f:
        f.write(f"{os.getpid()} {gc.pid}\\n")
    print(json.dumps({"event": "ready"}), flush=True)
    cmd = json.loads(sys.stdin.readline())
    assert cmd["cmd"] == "start"
    if mode == "crash" and first:
        sys.exit(3)
    n = 0
    while True:
        print(json.dumps({"event": "status", "t_sim_s": float(n), "sent": n, "rejected": {"x": 1}}), flush=True)
        if mode == "finish" and n == 3:
            print(json.dumps({"event": "done", "sent": n}), flush=True)
            sys.exit(0)
        line = sys.stdin.readline() if mode == "good" else None
        if line is not None and (not line or json.loads(line).get("cmd") == "stop"):
            sys.exit(0)
        time.sleep(0.05)
        n += 1
""")


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait(cond, timeout=15.0):
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        if cond():
            return True
        time.sleep(0.05)
    return False


@pytest.mark.slow
@pytest.mark.live
def test_supervisor_restarts_a_dead_worker_and_stops_everything(tmp_path):
    script = tmp_path / "dummy.py"
    script.write_text(DUMMY)
    ports = {m: _free_port() for m in ("crash", "good", "finish")}
    events = []
    sup = Supervisor(tmp_path / "logs", grace_s=0.5, term_timeout_s=2.0, on_event=events.append)
    for mode, port in ports.items():
        sup.add(mode, [sys.executable, str(script), mode, str(tmp_path), str(port)])
    try:
        sup.start_all()
        assert sup.wait_ready(30.0)
        sup.broadcast_start(time.time())
        assert _wait(lambda: (sup.poll() or True) and sup.children["crash"].restarts == 1
                     and sup.children["crash"].status.get("t_sim_s", 0) >= 2)
        assert _wait(lambda: (sup.poll() or True) and sup.children["finish"].finished)
        fin = sup.children["finish"]
        assert fin.exits == [0] and fin.done and fin.restarts == 0  # a clean end is not restarted
        crash = sup.children["crash"]
        assert crash.exits[0] == 3
        kinds = [(e["event"], e["worker"]) for e in events]
        assert ("restart", "crash") in kinds and ("restart", "good") not in kinds
        assert sup.alive() == ["crash", "good"]
    finally:
        how = sup.stop()
    pids = [int(p) for line in (tmp_path / "pids").read_text().split("\n") if line for p in line.split()]
    assert len(pids) == 8  # 4 incarnations (crash twice), each with a grandchild
    assert _wait(lambda: all(_dead(p) for p in pids), 10.0), [p for p in pids if not _dead(p)]
    assert all(_tcp_free(p) for p in ports.values())
    assert how["good"] == "exited"  # it honoured the stop command
    assert sup.all_finished() and not sup.alive()


@pytest.mark.live
def test_supervisor_kills_a_worker_that_ignores_sigterm(tmp_path):
    script = tmp_path / "dummy.py"
    script.write_text(DUMMY)
    port = _free_port()
    sup = Supervisor(tmp_path / "logs", grace_s=0.2, term_timeout_s=0.5)
    sup.add("stubborn", [sys.executable, str(script), "stubborn", str(tmp_path), str(port)])
    sup.start_all()
    assert sup.wait_ready(30.0)
    sup.broadcast_start(time.time())
    assert _wait(lambda: sup.children["stubborn"].status.get("t_sim_s", 0) >= 1)
    how = sup.stop()
    assert how["stubborn"] == "SIGKILL"
    pids = [int(p) for p in (tmp_path / "pids").read_text().split()]
    assert _wait(lambda: all(_dead(p) for p in pids), 10.0)
    assert _tcp_free(port)
    assert sup.children["stubborn"].exits == [-signal.SIGKILL]


# ------------------------------------------------------------------ replay = batch


@pytest.mark.slow
def test_replay_of_a_recorded_batch_run_gives_the_same_estimates(tmp_path):
    from sitl.app.batch import run_batch
    from sitl.app.launcher import replay
    from sitl.scenario import default_scenario

    scn = default_scenario().replace(run={"duration_s": 15.0}, mavlink={"enabled": False})
    log = tmp_path / "bus.log"
    res = run_batch(scn, record=log)
    assert res["recorded"] > 0
    rep = replay(log, scn)
    for kind in ("beacon", "sonde"):
        c = rep["vs_live"][kind]
        assert c["recorded"] > 10 and c["matched"] == c["recorded"] == c["replayed"]
        assert c["max_pos_diff_m"] == 0.0
    # the replay's own scoring (recorded truth) agrees with the batch run's
    for name, e in res["errors"].items():
        assert rep["errors"][name]["rmse_m"] == pytest.approx(e["rmse_m"], rel=1e-12)
    # a torn tail (a crash mid-write) still replays up to it
    data = log.read_bytes()
    log.write_bytes(data[: len(data) - 7])
    rep2 = replay(log, scn)
    assert rep2["torn_tail"]["dropped_bytes"] > 0 and rep2["records"] == rep["records"] - 1


# ------------------------------------------------------------------ mission upload


@pytest.mark.slow
def test_uploaded_mission_is_flown():
    import math

    import numpy as np

    from sitl.bus import InMemoryTransport
    from sitl.geodesy import ecef_to_geodetic, geodetic_to_ecef
    from sitl.scenario import default_scenario
    from vehicles.process import VehicleGroup

    scn = default_scenario().replace(sonde={"enabled": False})
    bus = InMemoryTransport()
    g = VehicleGroup(scn, [0, 1, 2], bus, np.random.SeedSequence(1), with_sonde=False)
    t0 = scn.run.t0_gps_s
    for k in range(3):
        g.step(t0 + k)
    lat, lon, h = (float(g.last_uav_truth.lat_rad[1]), float(g.last_uav_truth.lon_rad[1]),
                   float(g.last_uav_truth.h_m[1]))
    wp = (lat, lon + 8000.0 / (6.371e6 * math.cos(lat)), h)  # 8 km east, same height
    g.on_mission(1)([wp])
    W = np.array(geodetic_to_ecef(*wp))
    ref = VehicleGroup(scn, [0, 1, 2], InMemoryTransport(), np.random.SeedSequence(1), with_sonde=False)  # no mission
    for k in range(3):
        ref.step(t0 + k)
    d = []
    for k in range(3, 200):
        g.step(t0 + k)
        ref.step(t0 + k)
        d.append(float(np.linalg.norm(g.last_uav_truth.pos_ecef_m[1] - W)))
    assert d[0] > 7000.0 and min(d) < 200.0  # it reached the waypoint (accept radius 150 m)
    # the others still fly the scenario's law (the same truth as without the mission)
    for f in ("pos_ecef_m", "heading_rad"):
        assert np.array_equal(np.asarray(getattr(g.last_uav_truth, f))[[0, 2]],
                              np.asarray(getattr(ref.last_uav_truth, f))[[0, 2]]), f
    assert not np.allclose(g.last_uav_truth.pos_ecef_m[1], ref.last_uav_truth.pos_ecef_m[1], rtol=0, atol=100.0)
    # its published truth is the mission's path, consistent with its geodetic state
    la, _lon, _h = ecef_to_geodetic(g.last_uav_truth.pos_ecef_m[1])
    assert float(la) == pytest.approx(float(g.last_uav_truth.lat_rad[1]), abs=1e-9)


# ------------------------------------------------------------------ parameters over MAVLink


@pytest.mark.live
def test_param_set_reaches_the_group_and_a_sonde_set_is_vetoed():
    import numpy as np
    from pymavlink import mavutil

    from sitl.bus import InMemoryTransport
    from sitl.scenario import default_scenario
    from vehicles.process import VehicleGroup, _mav_telemetry, build_endpoints

    base = udp_base(4)
    gcs = mavutil.mavlink_connection("udpin:127.0.0.1:0", source_system=255)
    scn = default_scenario().replace(mavlink={"gcs": f"127.0.0.1:{gcs.port.getsockname()[1]}", "base_port": base,
                                              "tlog": False})
    g = VehicleGroup(scn, [0, 1, 2], InMemoryTransport(), np.random.SeedSequence(1))
    eps = build_endpoints(g, scn, "unused")
    u2 = mavutil.mavlink_connection(f"udpout:127.0.0.1:{base + 10}", source_system=255)
    s4 = mavutil.mavlink_connection(f"udpout:127.0.0.1:{base + 30}", source_system=255)
    try:
        t0 = scn.run.t0_gps_s
        q0 = g.nav_cfg.q_m2_s3
        u2.mav.param_set_send(2, 1, b"NAV_Q", 0.5, mavutil.mavlink.MAV_PARAM_TYPE_REAL32)
        s4.mav.param_set_send(4, 1, b"SND_ASCENT", 7.0, mavutil.mavlink.MAV_PARAM_TYPE_REAL32)
        got = {}
        for k in range(40):
            g.step(t0 + k)
            eps.step(t0 + k, _mav_telemetry(g.telemetry(), len(eps)))
            for c in (u2, s4):
                m = c.recv_match(type="PARAM_VALUE", blocking=False)
                if m is not None:
                    got[m.param_id] = m.param_value
            if len(got) == 2:
                break
            time.sleep(0.02)
        assert q0 != 0.5 and got["NAV_Q"] == 0.5
        assert g.nav.config.q_m2_s3 == 0.5 == g.nav_cfg.q_m2_s3  # the group's filters run with it
        assert got["SND_ASCENT"] == pytest.approx(g.flight.params.ascent_rate_m_s)  # vetoed: unchanged
        assert eps.counters["param_rejected"] == 1
    finally:
        eps.close()
        for c in (gcs, u2, s4):
            c.close()


def test_batch_mode_applies_the_scenarios_bus_fault_rules():
    """`--batch` with [faults]: a bus rule drops at the in-memory bus what it drops live at the
    publishers (uav 2's beacon measurements, all of them), seeded; MAVLink / Zenoh links are
    listed as not applied; the locator then hears 2 UAVs instead of 3."""
    from sitl.app.batch import run_batch
    from sitl.scenario import default_scenario, parse_scenario

    base = default_scenario().replace(run={"duration_s": 6.0}, mavlink={"enabled": False}, sonde={"enabled": False})
    faulted = parse_scenario('[faults]\n"bus:*/uav/2/beacon/**" = "loss=100%"\n"zenoh:gs" = "delay=10ms"\n').faults
    plain, lossy = run_batch(base), run_batch(dataclasses.replace(base, faults=faulted))
    n_plain = plain["gs"]["beacon_locator"]["accepted"]
    n_lossy = lossy["gs"]["beacon_locator"]["accepted"]
    assert n_plain == 3 * 7 and n_lossy == 2 * 7
    f = lossy["faults"]
    assert f["not_in_batch"] == ["zenoh:gs"] and f["injected"]["dropped_loss"] == 7
    assert "faults" not in plain


# ------------------------------------------------------------------ --instance / --base-port


def _opts(cls, **kw):
    from sitl.app.launcher import RunOptions
    if cls is RunOptions:
        kw.setdefault("scenario", "x.toml")
    return cls(**kw)


@pytest.mark.parametrize("cls", ["DemoOptions", "RunOptions"])
def test_instance_shifts_every_port_by_ten_n_as_ardupilot_sitl(cls):
    from sitl.app import launcher as la
    from sitl.scenario import default_scenario
    cls = getattr(la, cls)
    base = default_scenario().replace(bus={"listen": "tcp/127.0.0.1:7447"})
    scn = la._scenario_with_overrides(base, _opts(cls, instance=3))
    assert scn.mavlink.base_port == 5760 + 30 and scn.mavlink.gcs == "127.0.0.1:14580"
    assert scn.bus.listen == "tcp/127.0.0.1:7477"
    scn = la._scenario_with_overrides(default_scenario(), _opts(cls, instance=2))
    assert scn.bus.listen == "tcp/127.0.0.1:0"  # any free port stays any free port
    scn = la._scenario_with_overrides(default_scenario(), _opts(cls, base_port=6000, instance=1,
                                                                gcs="127.0.0.1:15000"))
    assert scn.mavlink.base_port == 6010 and scn.mavlink.gcs == "127.0.0.1:15000"  # --gcs as given
    scn = la._scenario_with_overrides(default_scenario(), _opts(cls, base_port=7000))
    assert scn.mavlink.base_port == 7000 and scn.mavlink.gcs == "127.0.0.1:14550"


@pytest.mark.parametrize("argv, text", [
    (["--instance", "-1"], "--instance: expected an integer in 0..5000"),
    (["--instance", "two"], "--instance: expected an integer"),
    (["--base-port", "80"], "--base-port: expected an integer in 1024..65000"),
    (["--base-port", "64000", "--instance", "200"], "--base-port / --instance: expected an integer in 1024..65000"),
])
@pytest.mark.parametrize("cmd", ["demo", "run"])
def test_bad_instance_or_base_port_is_one_line_exit_2_before_anything_starts(tmp_path, capsys, cmd, argv, text):
    from sitl.app.cli import main
    from sitl.scenario import DEFAULT_SCENARIO_TOML
    out = tmp_path / "out"
    pre = [cmd]
    if cmd == "run":
        (tmp_path / "s.toml").write_text(DEFAULT_SCENARIO_TOML)
        pre.append(str(tmp_path / "s.toml"))
    assert main(pre + ["--out", str(out)] + argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and text in err, err
    assert not out.exists() or not any(out.iterdir())



# ------------------------------------------------------------------ start-up: the kernels' cache


@pytest.fixture
def fake_tree(tmp_path, monkeypatch):
    """A package tree and a numba cache dir of the test's own (the real sources are not touched)."""
    from sitl.app import kernel_cache as kc
    pkg = tmp_path / "pkg"
    (pkg / "__pycache__").mkdir(parents=True)
    (pkg / "mod.py").write_text("x = 1\n")
    cache = tmp_path / "numba_cache"
    cache.mkdir()
    monkeypatch.setattr(kc, "_roots", lambda: [pkg])
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(cache))
    return kc, pkg, cache


def test_kernel_cache_is_warm_only_while_sources_and_cache_are_as_stamped(fake_tree):
    kc, pkg, cache = fake_tree
    assert not kc.is_warm()  # never warmed here
    assert kc.estimate() == (kc.DEFAULT_COLD_S, kc.DEFAULT_KERNELS)
    for k in range(3):
        (cache / f"mod.f{k}-1.py311.nbi").write_bytes(b"i")
    kc.mark_warm(42.0, 3)
    assert kc.is_warm() and kc.stamp_path().parent == cache
    assert kc.estimate()[0] in (42.0, kc.DEFAULT_COLD_S)
    st = (pkg / "mod.py").stat()
    os.utime(pkg / "mod.py", ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))  # a source changed
    assert not kc.is_warm()
    kc.mark_warm(1.0, 0)
    assert kc.is_warm()
    (cache / "mod.f0-1.py311.nbi").unlink()  # a cache file deleted
    assert not kc.is_warm()


def test_kernel_cache_estimate_is_the_last_cold_warm_up(fake_tree):
    kc, pkg, cache = fake_tree
    kc.mark_warm(63.4, 20)
    assert kc.estimate() == (63.4, 20)
    kc.mark_warm(2.1, 1)  # a warm re-run (one kernel): the cold figure stays
    assert kc.estimate() == (63.4, 20)


@pytest.mark.live
def test_a_cold_start_says_at_once_that_it_compiles_and_a_warm_one_skips_it(tmp_path, monkeypatch):
    from sitl.app import kernel_cache as kc
    from sitl.app.launcher import _cold_warm_up
    from sitl.scenario import default_scenario
    scn = default_scenario().replace(uavs={"count": 3}, sonde={"enabled": False})
    stamp = {}
    monkeypatch.setattr(kc, "is_warm", lambda: False)
    monkeypatch.setattr(kc, "mark_warm", lambda el, n: stamp.update(el=el, n=n))
    out = io.StringIO()
    assert _cold_warm_up(scn, tmp_path, threading.Event(), out)
    lines = out.getvalue().strip().splitlines()
    assert "compiling the estimation kernels (first run only, about" in lines[0] and "about" in lines[0] and lines[-1].startswith(
        "[launcher] kernels compiled")
    assert stamp["el"] > 0 and stamp["n"] >= 0
    monkeypatch.setattr(kc, "is_warm", lambda: True)
    out = io.StringIO()
    assert _cold_warm_up(scn, tmp_path / "warm", threading.Event(), out) and out.getvalue() == ""
    assert not (tmp_path / "warm").exists()  # nothing started, nothing written
