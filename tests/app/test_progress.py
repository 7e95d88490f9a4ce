"""A first run that talks (sitl/app/progress.py, the launcher's start lines): tqdm's bar with its
ETA on a terminal, one line per ~10 % when stderr is not one, nothing when quiet; a line as soon
as numba compiles kernels; the demo says where its output goes, how to connect MAVProxy or
QGroundControl on the scenario's real ports, and the report's path at the end."""
from __future__ import annotations

import io
import re
from pathlib import Path

from sitl.app import progress as pg


def test_not_a_tty_one_line_per_tenth_with_the_eta_and_no_bar():
    out = io.StringIO()
    p = pg.Progress("run", stream=out)
    assert not p.tty
    p("starting")
    for k in range(1, 201):
        p(f"k={k}", done=k, total=200)
    p.close()
    lines = out.getvalue().splitlines()
    assert lines[0] == "starting" and "\r" not in out.getvalue()
    meters = lines[1:]
    assert 10 <= len(meters) <= 11
    # tqdm's meter without its bar: percent, count, [elapsed<ETA, rate], then the message
    assert all(re.match(r"run:\s+\d+% \d+/200 \[\d\d:\d\d<\d\d:\d\d, .*\]  k=\d+$", m) for m in meters), meters
    assert meters[-1].startswith("run: 100%") and meters[-1].endswith("k=200")


def test_a_new_phase_when_done_goes_back_and_a_better_total():
    out = io.StringIO()
    p = pg.Progress("", stream=out)
    for case in ("a", "b"):
        for k in range(1, 11):
            p(case, done=k, total=10)
    p(done=5, total=5)  # a phase whose estimate grew: one line at 100 % of the corrected total
    p(done=9, total=9)
    p.close()
    lines = out.getvalue().splitlines()
    assert sum(line.endswith("  a") for line in lines) == 10 and sum(line.endswith("  b") for line in lines) == 10
    assert "9/9" in lines[-1]


def test_on_a_terminal_tqdm_draws_the_bar_in_place():
    out = io.StringIO()
    p = pg.Progress("run", stream=out, tty=True)
    for k in range(1, 51):
        p("x", done=k, total=50)
    p("a plain line")
    p.close()
    text = out.getvalue()
    assert "\r" in text and "50/50" in text and "100%" in text and "a plain line\n" in text


def test_quiet_says_nothing():
    assert pg.progress_printer(True, "x") is None
    assert isinstance(pg.progress_printer(False, "x"), pg.Progress)


def test_the_compile_notice_speaks_only_when_kernels_are_compiled(monkeypatch):
    from sitl.app import kernel_cache as kc

    monkeypatch.setattr(pg, "LINE_EVERY_S", 0.0)
    monkeypatch.setattr(kc, "estimate", lambda: (42.0, 20))
    out = io.StringIO()
    monkeypatch.setattr(kc, "written_since", lambda t: 0)
    with pg.KernelCompileNotice(stream=out, poll_s=0.01) as n:
        import threading
        threading.Event().wait(0.1)
    assert out.getvalue() == "" and n.compiled == 0
    count = iter(range(1, 10_000))
    monkeypatch.setattr(kc, "written_since", lambda t: min(next(count), 7))
    with pg.KernelCompileNotice(stream=out, poll_s=0.01):
        threading.Event().wait(0.2)
    lines = out.getvalue().splitlines()
    assert lines[0] == "compiling the estimation kernels (first run only, about 42 s)"
    assert "compiling the estimation kernels: 7/~20 compiled" in lines
    assert lines[-1] == "compiled 7 kernels (cached: later runs skip this)"
    with pg.KernelCompileNotice(enabled=False) as n:  # quiet
        assert n._thread is None


def test_the_demo_says_where_its_output_goes_and_the_real_ports():
    from sitl.app.launcher import start_text
    from sitl.scenario import default_scenario

    scn = default_scenario().replace(uavs={"count": 2}, mavlink={"gcs": "127.0.0.1:14560", "base_port": 6000,
                                                                  "tcp": False})
    text = start_text(scn, Path("out/x"))
    assert "out/x/" in text and "report.json" in text
    assert "udp:127.0.0.1:14560" in text or "udpin:127.0.0.1:14560" in text
    for i, port in enumerate((6000, 6010, 6020)):  # UAV 1, UAV 2, the sonde after them
        assert f"system id {i + 1}): `mavproxy.py --master udpout:127.0.0.1:{port}`" in text
    assert "tcp:" not in text
    text = start_text(default_scenario(), Path("o"))
    assert "QGroundControl's default UDP link" in text and "--master tcp:127.0.0.1:5760" in text


def test_a_batch_demo_prints_its_progress_and_the_reports_path(tmp_path, capsys):
    from sitl.app.cli import main

    assert main(["demo", "--batch", "--duration", "300", "--out", str(tmp_path)]) == 0
    cap = capsys.readouterr()
    assert f"report: {tmp_path / 'report.json'}" in cap.out.splitlines()
    meters = [line for line in cap.err.splitlines() if line.startswith("batch run:")]
    assert meters and all(re.search(r"\d+% \d+/300 \[\d\d:\d\d<\d\d:\d\d", m) for m in meters), cap.err
