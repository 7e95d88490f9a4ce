"""`skyfuse bench live` and `skyfuse bench mavlink` end to end on a tiny swarm: the figures
they print exist and add up (no assertion on their speed: benchmarks measure that)."""
import json

import pytest

from sitl.app.cli import main

pytestmark = [pytest.mark.live, pytest.mark.slow]


def test_bench_live_reports_command_acks_and_the_tick_breakdown(tmp_path, capsys):
    out = tmp_path / "bl.json"
    assert main(["bench", "live", "--uavs", "12", "--duration", "6", "--out", str(tmp_path / "o"),
                 "--json", str(out)]) == 0
    run = json.loads(out.read_text())["runs"][0]
    ack = run["command_ack_ms"]
    # a GCS socket's commands to the vehicles were answered (each ACK matched to its command)
    assert ack["answered"] > 0 and ack["answered"] <= ack["sent"] and ack["p50"] <= ack["p95"] <= ack["max"]
    parts = run["vehicle_tick_parts_ms"][0]
    assert set(parts) == {"input", "world", "bus_put", "streams", "cpu"}
    assert all(v["p50"] <= v["p99"] <= v["max"] for v in parts.values())
    printed = capsys.readouterr().out
    assert "COMMAND_LONG -> COMMAND_ACK" in printed and "world tick p50/p99 ms" in printed


def test_bench_mavlink_sends_the_same_frames_in_fewer_datagrams(tmp_path, capsys):
    out = tmp_path / "bm.json"
    assert main(["bench", "mavlink", "--uavs", "10", "--duration", "2", "--rounds", "1", "--json", str(out)]) == 0
    pair = json.loads(out.read_text())["pairs"][0]
    a, b = pair["pymavlink"], pair["batched"]
    assert a["packets_sent"] == b["packets_sent"] > 0
    assert a["datagrams_sent"] == a["packets_sent"] and b["datagrams_sent"] < a["datagrams_sent"]
    assert "batched / pymavlink CPU median" in capsys.readouterr().out
