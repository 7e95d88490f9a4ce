"""`skyfuse bench sonde`: runs on a tiny flight, writes its JSON, refuses bad flags."""
from __future__ import annotations

import json

import pytest

from sitl.app.cli import main


def test_bench_sonde_tiny_run(tmp_path, capsys):
    out = tmp_path / "bench.json"
    rc = main(["bench", "sonde", "--duration", "20", "--rounds", "1", "--no-trio", "--quiet", "--json", str(out)])
    assert rc == 0
    res = json.loads(out.read_text(), parse_constant=lambda c: pytest.fail(f"non-strict JSON {c}"))
    assert res["bench"] == "sonde" and res["epochs"] == 21 and res["main"] == "fused_no_bus"
    keys = [r["key"] for r in res["rows"]]
    assert keys == ["fused_no_bus", "fused_bus", "world"]
    for r in res["rows"]:
        assert r["wall_s"] > 0 and r["x_real_time"] == pytest.approx(20.0 / r["wall_s"])
    assert res["rows"][0]["ratio_to_main"] == 1.0
    assert 0 < res["fused_tracker_s"] < res["rows"][0]["wall_s"] and 15 <= res["estimates"] <= 21
    assert "x real time" in capsys.readouterr().out


@pytest.mark.parametrize("argv", [["--duration", "0"], ["--rounds", "0"], ["--seed", "-1"], ["--bogus"],
                                  ["--json", "/nonexistent-dir/x.json"]])
def test_bench_sonde_bad_flags_exit_2(argv, capsys):
    rc = main(["bench", "sonde", "--quiet"] + argv)
    err = capsys.readouterr().err
    assert rc == 2
    assert len(err.strip().splitlines()) == 1 and err.startswith("error:")
