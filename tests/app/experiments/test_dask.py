"""Monte Carlo chunks on Dask (sitl.app.cluster): the `--dask` values; the sonde and long-run
experiments on a LocalCluster against the same runs in this process (result.json equal but for
timings and provenance, which records the same scenario hash; the sonde's raw arrays equal bit
for bit over several chunks, and to rounding for another chunking); a failed chunk and a dead
worker named in one line; no process or port left behind."""
from __future__ import annotations

import json
import math
import os
import socket

import numpy as np
import pytest

from sitl.app import cluster
from sitl.app.cli import main
from sitl.params import ParamError

needs_dask = pytest.mark.skipif(not cluster.available(), reason="dask and distributed are not installed "
                                                                "(the optional extra: pip install '.[dask]')")

#: result.json keys that are measured times, or where and when the run was (not results)
NOT_RESULTS = {"provenance", "wall_s", "wall_s_per_trial", "one_trial_wall_s", "timing_s", "bus_cost_implied_s",
               "bus_cost_per_message_us", "wall_s_pcrb"}


def _results(path) -> dict:
    doc = json.loads(path.read_text(encoding="utf-8"))
    return {k: v for k, v in doc.items() if k not in NOT_RESULTS}


def _children() -> set:
    """This process's live child processes (pid, command line), multiprocessing's resource tracker
    aside (it lives as long as the interpreter)."""
    import psutil

    out = set()
    for p in psutil.Process().children(recursive=True):
        try:
            if p.status() == psutil.STATUS_ZOMBIE:
                continue
            cmd = " ".join(p.cmdline())
        except psutil.NoSuchProcess:
            continue
        if "resource_tracker" not in cmd:
            out.add((p.pid, cmd))
    return out


def _port_free(address: str) -> bool:
    """Whether nothing listens on ``address``'s port any more (closed connections in TIME_WAIT
    aside: SO_REUSEADDR, as every server sets)."""
    host, port = address.rsplit("/", 1)[-1].rsplit(":", 1)
    with socket.socket() as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, int(port)))
            s.listen(1)
        except OSError:
            return False
    return True


# ------------------------------------------------------------------ the option
@pytest.mark.parametrize("text, workers, address", [
    ("local", os.cpu_count() or 1, None), ("local:3", 3, None), ("tcp://10.0.0.2:8786", None, "tcp://10.0.0.2:8786"),
    ("tcp://scheduler.lan:1", None, "tcp://scheduler.lan:1")])
def test_spec_values(text, workers, address):
    spec = cluster.parse_spec(text)
    assert (spec.workers, spec.address, spec.local) == (workers, address, address is None)


@pytest.mark.parametrize("text", ["", "local:0", "local:x", "locale", "tcp://host", "tcp://host:0", "tcp://host:70000",
                                  "http://host:8786", "host:8786", "tcp://a b:1"])
def test_spec_rejected_in_one_line(text):
    with pytest.raises(ParamError) as exc:
        cluster.parse_spec(text)
    assert "\n" not in str(exc.value) and "expected" in str(exc.value)


@pytest.mark.parametrize("argv, says", [
    (["--dask", "local:0"], "expected local:N with N >= 1"),
    (["--dask", "tcp://h"], "expected local, local:N or tcp://HOST:PORT"),
    (["--dask", "local", "--seeds", "2"], "--dask: the seed study"),
])
def test_cli_usage_error_exit_2_before_anything(argv, says, tmp_path, capsys):
    out = tmp_path / "out"
    rc = main(["experiment", "sonde", "--trials", "1", "--duration", "30", "--out", str(out), "--quiet", *argv])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.count("\n") == 1 and says in err and "Traceback" not in err
    assert not (out / "result.json").exists()


# ------------------------------------------------------------------ on a LocalCluster
@pytest.fixture(scope="module")
def pool():
    if not cluster.available():
        pytest.skip("dask and distributed are not installed (the optional extra: pip install '.[dask]')")
    before = _children()
    with cluster.TrialPool("local:2") as p:
        address = p.cluster.scheduler_address
        yield p
    assert _children() <= before, "a worker process outlived the pool"
    assert _port_free(address), f"the scheduler's port {address} is still bound"


def _sonde_scenario():
    from sitl.app.experiments.sonde import SondeScenario

    return SondeScenario(duration_s=120.0)


RAW_ARRAYS = ("trials", "t_gps_s", "ground_range_m", "slant_range_m", "alt_m", "burst_alt_m", "truth_pos", "truth_vel",
              "pos", "vel", "cov", "count")


def _assert_raw_equal(a: dict, b: dict) -> None:
    for k in RAW_ARRAYS:
        np.testing.assert_array_equal(np.asarray(a[k]), np.asarray(b[k]), err_msg=k, strict=True)
    assert a["counters"] == b["counters"] and a["bus"] == b["bus"] and a["integrity_events"] == b["integrity_events"]


@needs_dask
@pytest.mark.live
@pytest.mark.slow
def test_sonde_chunks_on_dask_equal_the_one_process_run(pool):
    from sitl.app.experiments import sonde

    scn = _sonde_scenario()
    here = sonde.run(scn, 3, 7, batch=2)  # chunks [0, 1], [2]
    on_dask = sonde.run(scn, 3, 7, batch=2, pool=pool)
    _assert_raw_equal(here, on_dask)
    assert np.isfinite(here["pos"][0]).any()  # the comparison is of real estimates, not of empty arrays
    # another chunking (one chunk of 3) draws the same trials (a SeedSequence child per trial: the
    # truth is the same, bit for bit), but the trackers' batched arithmetic rounds differently with
    # the batch size: their estimates agree to rounding only (measured over 120 s: 6e-7 m on the
    # positions, 7e-8 m/s on the velocities), not bit for bit. A Dask run keeps the one-process
    # chunking, so its result is the one-process result exactly (above).
    other = sonde.run(scn, 3, 7, batch=3)
    for k in ("trials", "t_gps_s", "ground_range_m", "slant_range_m", "alt_m", "burst_alt_m", "truth_pos",
              "truth_vel", "count"):
        np.testing.assert_array_equal(np.asarray(other[k]), np.asarray(on_dask[k]), err_msg=k, strict=True)
    for k, tol in (("pos", 1e-4), ("vel", 1e-5)):  # m, m/s: far below the trackers' errors (metres)
        np.testing.assert_allclose(other[k], on_dask[k], rtol=0, atol=tol, equal_nan=True, err_msg=k)


@needs_dask
@pytest.mark.live
def test_failed_chunk_named_in_one_line(pool):
    with pytest.raises(cluster.ClusterError) as exc:
        pool.map(math.sqrt, [(4.0,), (-1.0,)], labels=["trials 0-0", "trials 1-1"])
    msg = str(exc.value)
    assert "\n" not in msg
    assert msg.startswith("dask: trials 1-1 failed on worker tcp://127.0.0.1:")
    assert msg.endswith("ValueError: math domain error")
    assert pool.map(math.sqrt, [(4.0,), (9.0,)]) == [2.0, 3.0]  # the pool goes on


@needs_dask
@pytest.mark.live
@pytest.mark.slow
def test_dead_worker_named_in_one_line(pool):
    with pytest.raises(cluster.ClusterError) as exc:
        pool.map(os._exit, [(3,)], labels=["trials 5-9"])
    msg = str(exc.value)
    assert "\n" not in msg and msg.startswith("dask: trials 5-9: its worker died (2 attempt(s), last on tcp://127.0.0.1:")
    pool.client.wait_for_workers(2, timeout=60)  # the nannies restart their workers
    assert pool.map(math.sqrt, [(16.0,)]) == [4.0]


@needs_dask
def test_unreachable_scheduler_one_line():
    with socket.socket() as s:  # a loopback port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(cluster.ClusterError) as exc:
        with cluster.TrialPool(f"tcp://127.0.0.1:{port}"):
            pass
    assert str(exc.value).startswith(f"dask: cannot connect to the scheduler tcp://127.0.0.1:{port}:")
    assert "\n" not in str(exc.value)


@needs_dask
@pytest.mark.live
@pytest.mark.slow
def test_sonde_command_on_dask_writes_the_same_result(tmp_path, capsys):
    common = ["experiment", "sonde", "--trials", "2", "--duration", "120", "--seed", "5"]
    before = _children()
    assert main([*common, "--out", str(tmp_path / "here"), "--quiet"]) == 0
    assert main([*common, "--out", str(tmp_path / "dask"), "--dask", "local:2"]) == 0
    err = capsys.readouterr().err
    assert "dask: local cluster tcp://127.0.0.1:" in err and "2 worker(s)" in err  # where the chunks ran
    assert _children() <= before, "the command left a worker process behind"
    a, b = _results(tmp_path / "here" / "result.json"), _results(tmp_path / "dask" / "result.json")
    assert a["trials"] == 2 and a == b


@needs_dask
@pytest.mark.live
@pytest.mark.slow
def test_long_run_command_on_dask_writes_the_same_result(tmp_path):
    common = ["experiment", "long-run", "--duration", "120", "--window", "120", "--settle", "60", "--trials", "2",
              "--no-sonde", "--no-pcrb", "--seed", "3", "--quiet"]
    before = _children()
    assert main([*common, "--out", str(tmp_path / "here")]) == 0
    assert main([*common, "--out", str(tmp_path / "dask"), "--dask", "local:2"]) == 0  # a trial per task
    assert _children() <= before, "the command left a worker process behind"
    a, b = _results(tmp_path / "here" / "result.json"), _results(tmp_path / "dask" / "result.json")
    assert a["trials"] == 2 and a["windows"][0]["epochs"] > 0 and a == b
    pa, pb = (json.loads((tmp_path / d / "result.json").read_text())["provenance"] for d in ("here", "dask"))
    assert pa["scenario_sha256"] == pb["scenario_sha256"]  # how the trials ran is not the scenario
    assert "--dask" in pb["command_line"]
