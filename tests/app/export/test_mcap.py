"""`skyfuse export mcap`: read back with the `mcap` library, one channel per bus key, a schema
per message type, message counts equal to the bus log's, log_time from the record's receive
time and publish_time from the message's simulated time (as UTC); bad input: one line, exit 2,
no traceback, nothing written; a torn tail: exported up to it, said once."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from collections import Counter
from datetime import datetime, timedelta, timezone

import pytest
from mcap.reader import make_reader

from sitl.app.cli import main

from .conftest import RECV_LAG_S, T0, beacon_llh, ecef


def _utc_ns(t_gps_s: float) -> int:
    dt = datetime(1980, 1, 6, tzinfo=timezone.utc) + timedelta(seconds=t_gps_s - 18)
    return int(round(dt.timestamp() * 1e6)) * 1000


def conforms(value, schema) -> bool:
    """The JSON Schema keywords the export uses (type, properties, required, additionalProperties,
    items, minItems, maxItems), checked by hand (no JSON Schema validator is installed)."""
    types = schema.get("type")
    if types is not None:
        names = types if isinstance(types, list) else [types]
        kinds = {"number": (int, float), "integer": (int,), "boolean": (bool,), "string": (str,),
                 "array": (list,), "object": (dict,), "null": (type(None),)}
        ok = any(isinstance(value, kinds[n]) and not (n in ("number", "integer") and isinstance(value, bool))
                 for n in names)
        if not ok:
            return False
    if isinstance(value, dict):
        props = schema.get("properties", {})
        if any(k not in value for k in schema.get("required", [])):
            return False
        if schema.get("additionalProperties") is False and set(value) - set(props):
            return False
        return all(conforms(v, props[k]) for k, v in value.items() if k in props)
    if isinstance(value, list):
        if len(value) < schema.get("minItems", 0) or len(value) > schema.get("maxItems", len(value)):
            return False
        return all(conforms(v, schema.get("items", {})) for v in value)
    return True


def _read(path):
    with open(path, "rb") as f:
        r = make_reader(f)
        summary = r.get_summary()
        msgs = [(s, c, m) for s, c, m in r.iter_messages(log_time_order=False)]
        meta = {m.name: m.metadata for m in r.iter_metadata()}
    return summary, msgs, meta


def test_mcap_round_trip(synthetic_run, capsys):
    out = synthetic_run.path.parent / "bus.mcap"
    assert main(["export", "mcap", str(synthetic_run.path)]) == 0
    assert "1 undecodable" in capsys.readouterr().out
    summary, msgs, meta = _read(out)
    topics = Counter(c.topic for _, c, _ in msgs)
    good = {k: n for k, n in synthetic_run.per_key.items()}
    # one channel per bus key, each with the bus log's count; the undecodable payload on its own channel
    assert sorted(c.topic for c in summary.channels.values()) == sorted([*good, "skyfuse/undecodable"])
    assert {k: topics[k] for k in good} == good and topics["skyfuse/undecodable"] == 1
    assert sum(topics.values()) == synthetic_run.records == summary.statistics.message_count
    # a schema per message type, JSON Schema, JSON messages
    names = {s.name for s in summary.schemas.values()}
    assert names == {"skyfuse.bus.v3.Truth", "skyfuse.bus.v3.Estimate", "skyfuse.bus.v3.UavNav",
                     "skyfuse.bus.v3.RadarMeasurement", "skyfuse.bus.Undecodable"}
    assert all(s.encoding == "jsonschema" for s in summary.schemas.values())
    assert all(c.message_encoding == "json" for c in summary.channels.values())
    for sch, ch, m in msgs:
        doc = json.loads(m.data)
        js = json.loads(sch.data)
        assert set(doc) == set(js["required"]), ch.topic
        assert conforms(doc, js), ch.topic
        if ch.topic == "skyfuse/undecodable":
            assert doc["key"] == "r1/uav/7/nav" and doc["reason"]
            continue
        assert m.publish_time == _utc_ns(doc["t_gps_s"])
        if ch.topic.startswith("r1/radar/"):  # recorded before the recorder's clock started: -inf
            assert m.log_time == m.publish_time
        else:
            assert m.log_time == _utc_ns(doc["t_gps_s"] + RECV_LAG_S)
    truth = [json.loads(m.data) for _, c, m in msgs if c.topic == "r1/truth/beacon/b1"]
    assert truth[0]["pos_ecef_m"] == pytest.approx(list(ecef(*beacon_llh(0))), abs=1e-6)
    est = [json.loads(m.data) for _, c, m in msgs if c.topic == "r1/gs/estimate/beacon/b1"]
    assert len(est[0]["cov"]) == 6 and all(len(row) == 6 for row in est[0]["cov"]) and est[0]["nis"] == 1.5
    assert not conforms({**est[0], "cov": est[0]["cov"][:5]}, json.loads(
        next(s for s in summary.schemas.values() if s.name.endswith(".Estimate")).data))  # the checker bites
    assert meta["skyfuse"]["schema"] == "skyfuse.export.mcap/1"
    assert int(meta["skyfuse"]["records"]) == synthetic_run.records
    assert _utc_ns(T0) == 1735693182 * 10**9  # 2025-01-01T00:59:42Z


def test_torn_tail_is_exported_up_to_it_and_said_once(synthetic_run, capsys):
    log = synthetic_run.path
    data = log.read_bytes()
    torn = log.parent / "torn.log"
    torn.write_bytes(data[:-7])  # the last record cut short
    out = log.parent / "torn.mcap"
    assert main(["export", "mcap", str(torn), "-o", str(out)]) == 0
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "torn record" in err
    summary, _, _ = _read(out)
    assert summary.statistics.message_count == synthetic_run.records - 1


@pytest.mark.parametrize("content", [b"", b"hello, this is not a bus log at all", b"SKYFBUS\x01rest"])
def test_not_a_bus_log_is_one_line_exit_2_nothing_written(tmp_path, capsys, content):
    bad = tmp_path / "notalog.bin"
    bad.write_bytes(content)
    before = sorted(os.listdir(tmp_path))
    assert main(["export", "mcap", str(bad)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and err.startswith("error: export mcap:")
    assert sorted(os.listdir(tmp_path)) == before


@pytest.mark.parametrize("argv", [["export", "mcap", "{d}/missing.log"], ["export", "mcap", "{d}"],
                                  ["export", "table", "{d}"], ["export", "kml", "{d}/missing"]])
def test_missing_inputs_are_one_line_exit_2(tmp_path, capsys, argv):
    assert main([a.format(d=tmp_path) for a in argv]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and os.listdir(tmp_path) == []


@pytest.mark.live
def test_console_script_on_a_non_log_file_has_no_traceback(tmp_path):
    bad = tmp_path / "x.txt"
    bad.write_text("plain text\n")
    env = dict(os.environ)
    proc = subprocess.run([sys.executable, "-m", "sitl.app.cli", "export", "mcap", str(bad)],
                          capture_output=True, text=True, timeout=60, env=env)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr and proc.stderr.count("\n") == 1
    assert sorted(os.listdir(tmp_path)) == ["x.txt"]


def test_progress_bar_on_a_terminal(synthetic_run, capsys):
    from sitl.app.export.source import read_records

    n = sum(1 for _ in read_records(synthetic_run.path, progress=True, desc="reading"))
    assert n == synthetic_run.records
    assert "reading" in capsys.readouterr().err  # tqdm's bar, on stderr
