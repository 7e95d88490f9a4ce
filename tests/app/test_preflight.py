"""Operator mistakes cost one line and exit 2, before anything starts (issue 19): a second run
into an output directory in use, a port already bound, an unreadable signing key file, a bus
log that holds nothing; and the status line marks estimates that stopped coming."""
from __future__ import annotations

import socket
from pathlib import Path

from tests.procs import udp_base

from sitl.app.cli import main
from sitl.app.preflight import OutDirLock
from sitl.app.status import format_status
import pytest


def _scenario(tmp_path: Path, **mavlink) -> Path:
    lines = ["[run]", "duration_s = 5.0", "[mavlink]"] + [f"{k} = {v!r}".replace("'", '"') for k, v in mavlink.items()]
    p = tmp_path / "scn.toml"
    p.write_text("\n".join(lines) + "\n")
    return p


def _one_line_exit_2(argv, capsys) -> str:
    assert main(argv) == 2
    cap = capsys.readouterr()
    err = cap.err.strip()
    assert err.count("\n") == 0 and err.startswith("error: ") and "Traceback" not in cap.err + cap.out, cap
    return err


def _nothing_started(out: Path) -> None:
    # the launcher writes these as soon as it starts a router, a worker or the bus log
    for name in ("run.json", "bus.log", "specs", "logs", "report.json"):
        assert not (out / name).exists(), name


def test_a_second_run_into_a_directory_in_use_is_refused(tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "bus.log").write_bytes(b"the running run's records")
    with OutDirLock(out):  # a run holds it
        err = _one_line_exit_2(["demo", "--duration", "5", "--out", str(out)], capsys)
    assert "in use by another skyfuse run" in err and "--out" in err
    assert (out / "bus.log").read_bytes() == b"the running run's records"  # not truncated
    # once released, the directory can be used again (the lock dies with its holder)
    with OutDirLock(out):
        pass


def test_batch_runs_take_the_lock_too(tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    with OutDirLock(out):
        err = _one_line_exit_2(["demo", "--batch", "--duration", "5", "--out", str(out)], capsys)
    assert "in use" in err


@pytest.mark.live
def test_a_mavlink_port_in_use_is_found_before_anything_starts(tmp_path, capsys):
    base = udp_base(4)
    out = tmp_path / "out"
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", base + 10))  # vehicle 1's port
        err = _one_line_exit_2(["run", str(_scenario(tmp_path, base_port=base)), "--out", str(out)], capsys)
    assert f"UDP port {base + 10}" in err and "base_port" in err and "system id 2" in err
    _nothing_started(out)


@pytest.mark.live
def test_a_router_port_in_use_is_found_before_anything_starts(tmp_path, capsys):
    out = tmp_path / "out"
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        p = tmp_path / "scn.toml"
        p.write_text(f'[run]\nduration_s = 5.0\n[bus]\nlisten = "tcp/127.0.0.1:{port}"\n[mavlink]\nenabled = false\n')
        err = _one_line_exit_2(["run", str(p), "--out", str(out)], capsys)
    assert f"TCP port {port}" in err and "[bus] listen" in err
    _nothing_started(out)


def test_a_missing_or_empty_signing_key_file_is_found_before_anything_starts(tmp_path, capsys):
    out = tmp_path / "out"
    missing = tmp_path / "nope.key"
    err = _one_line_exit_2(["run", str(_scenario(tmp_path, signing_key_file=str(missing))), "--out", str(out)], capsys)
    assert "signing_key_file" in err and "nope.key" in err and "cannot be read" in err
    _nothing_started(out)
    empty = tmp_path / "empty.key"
    empty.write_bytes(b"  \n")
    err = _one_line_exit_2(["run", str(_scenario(tmp_path, signing_key_file=str(empty))), "--out", str(out)], capsys)
    assert "is empty" in err


def test_replay_of_a_log_with_no_records_or_an_old_version_is_a_usage_error(tmp_path, capsys):
    from sitl.bus.buslog import MAGIC
    empty = tmp_path / "bus.log"
    empty.write_bytes(MAGIC)
    assert "holds no records" in _one_line_exit_2(["replay", str(empty)], capsys)
    old = tmp_path / "old.log"
    old.write_bytes(MAGIC[:7] + b"\x01")
    assert "version 1 is not supported" in _one_line_exit_2(["replay", str(old)], capsys)


def _snap(**kw):
    base = {"t_sim_s": 1e9 + 100.0, "vehicles": 4, "msgs_per_s": 10.0, "rejected_total": 0, "errors_m": {},
            "estimate_age_s": {}, "alive": 2, "restarts": 0}
    return {**base, **kw}


def test_the_status_line_marks_an_estimate_that_stopped_coming():
    fresh = format_status(_snap(errors_m={"beacon": 5.0, "sonde": 1.5},
                                estimate_age_s={"beacon": 0.5, "sonde": 0.5}), 1e9, 600.0, 3.0)
    assert "STALE" not in fresh and "old)" not in fresh and "5.0 m" in fresh
    aging = format_status(_snap(errors_m={"beacon": 5.0}, estimate_age_s={"beacon": 2.4}), 1e9, 600.0, 3.0)
    assert "(2 s old)" in aging and "STALE" not in aging
    stale = format_status(_snap(errors_m={"beacon": 5.0, "sonde": 1.5},
                                estimate_age_s={"beacon": 42.0, "sonde": 0.5}), 1e9, 600.0, 3.0)
    assert "beacon err      5.0 m STALE 42 s" in stale and stale.count("STALE") == 1
