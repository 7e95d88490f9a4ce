"""`skyfuse bench beacon`: runs on a tiny case, reports its peers, and rejects bad flags (exit 2)."""
from __future__ import annotations

import json

import pytest

from sitl.app.cli import build_parser, main


def test_help_lists_the_flags(capsys):
    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args(["bench", "beacon", "--help"])
    assert exc.value.code == 0
    text = capsys.readouterr().out
    for flag in ("--duration", "--uavs", "--case", "--rounds", "--seed", "--json", "--quiet"):
        assert flag in text


def test_tiny_run_reports_every_peer(tmp_path, capsys):
    out = tmp_path / "bench.json"
    assert main(["bench", "beacon", "--duration", "12", "--rounds", "1", "--quiet", "--json", str(out)]) == 0
    table = capsys.readouterr().out
    assert "x real time" in table and "trial through the bus" in table and "world only" in table
    res = json.loads(out.read_text())
    assert res["bench"] == "beacon" and res["duration_s"] == 12.0 and res["epochs"] == 13
    assert [r["key"] for r in res["rows"]] == ["bus", "direct", "world", "truth", "bus_only"]
    for r in res["rows"]:
        assert r["wall_s"] > 0 and r["x_real_time"] == pytest.approx(12.0 / r["wall_s"])
    assert res["rows"][0]["ratio_to_main"] == 1.0
    # the trial went through the bus, and the locator fed directly got the same estimates
    assert res["bus_equals_direct"] is True
    assert res["messages_published"] == res["trial_bus"]["published"] > 13 * 10
    assert res["locator_counters"]["accepted"] == 13 * 3
    assert res["trial_bus"]["rejected"] == {} and res["trial_bus"]["callback_errors"] == 0


@pytest.mark.parametrize("extra, needle", [
    (["--duration", "-5"], "--duration"),
    (["--duration", "5"], "at least 10"),
    (["--duration", "40000"], "at most 36000"),
    (["--duration", "abc"], "--duration"),
    (["--uavs", "2"], "--uavs"),
    (["--uavs", "101"], "at most 100"),
    (["--rounds", "0"], "positive integer"),
    (["--seed", "-1"], "integer >= 0"),
    (["--case", "nonsense"], "invalid choice"),
    (["--json", "/nonexistent-dir/x.json"], "--json"),
])
def test_bad_flags_exit_2_with_one_line(extra, needle, capsys):
    assert main(["bench", "beacon", *extra]) == 2
    err = capsys.readouterr().err
    assert needle in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err
