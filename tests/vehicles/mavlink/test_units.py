"""The MAVLink endpoint's pure parts: framing, signing checks, key files, unit conversions,
the parameter store (no sockets)."""
from __future__ import annotations

import hashlib
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from sitl.timescales import gps_seconds_from_utc, utc_from_gps_seconds
from vehicles.mavlink import ParamError, ParamSpec, ParamStore, listen_port, load_signing_key, split_datagram
from vehicles.mavlink import telemetry as tm
from sitl.mavlink.framing import SignatureChecker

KEY = hashlib.sha256(b"skyfuse test key").digest()


def _packets(n, signed=False, seed=0):
    rng = np.random.default_rng(seed)
    m = mavlink2.MAVLink(None, srcSystem=255, srcComponent=190)
    if signed:
        m.signing.secret_key, m.signing.sign_outgoing, m.signing.timestamp = KEY, True, 10**12
    out = []
    for _ in range(n):
        msg = m.param_request_read_encode(1, 1, b"P%d" % rng.integers(100), int(rng.integers(-1, 50)))
        out.append(msg.pack(m))
        m.seq = (m.seq + 1) % 256
    return out


# ---------------------------------------------------------------------------- framing
@settings(max_examples=200, deadline=None, derandomize=True)
@given(st.binary(max_size=400))
def test_split_never_raises_and_accounts_every_byte_run(data):
    frames, rejects = split_datagram(data)
    assert set(rejects) <= {"garbage", "truncated"}
    assert sum(len(f.buf) for f in frames) <= len(data)
    if data and not frames:
        assert rejects  # something non-empty that is not a frame is always counted


@settings(max_examples=100, deadline=None, derandomize=True)
@given(st.lists(st.binary(min_size=1, max_size=30).map(lambda b: bytes(x for x in b if x not in (0xFD, 0xFE))),
                min_size=1, max_size=5), st.integers(1, 4), st.booleans())
def test_split_finds_every_packet_between_junk_without_start_bytes(junks, n, signed):
    pkts = _packets(n, signed=signed)
    blob = b"".join(j + p for j, p in zip(junks * n, pkts))
    frames, rejects = split_datagram(blob)
    assert [f.buf for f in frames] == pkts
    assert [f.signed for f in frames] == [signed] * n and {f.msgid for f in frames} == {20}
    assert rejects.count("garbage") == sum(1 for j in (junks * n)[:n] if j)


def test_split_truncated_and_v1():
    p = _packets(1)[0]
    assert split_datagram(p[:-1]) == ([], ["truncated"])
    assert split_datagram(b"\xfd\x05") == ([], ["truncated"])
    v1 = mavlink2.MAVLink(None, srcSystem=3, srcComponent=4)
    buf = v1.heartbeat_encode(6, 8, 0, 0, 0).pack(v1, force_mavlink1=True)
    (f,), rej = split_datagram(buf)
    assert (f.version, f.sysid, f.compid, f.msgid, rej) == (1, 3, 4, 0, [])


# ---------------------------------------------------------------------------- signing
def test_signature_checker_against_pymavlink():
    pkts = _packets(3, signed=True)
    chk = SignatureChecker(KEY)
    frames = [split_datagram(p)[0][0] for p in pkts]
    ours = 10**12
    assert [chk.check(f, ours) for f in frames] == [None] * 3
    assert chk.check(frames[1], ours) == "replayed"  # older than the stream's last
    # pymavlink agrees on each signature (the independent implementation)
    peer = mavlink2.MAVLink(None)
    peer.signing.secret_key = KEY
    for p in pkts:
        assert peer.decode(bytearray(p))._signed
    assert SignatureChecker(bytes(32)).check(frames[0], ours) == "bad_signature"
    assert chk.check(split_datagram(_packets(1)[0])[0][0], ours) == "unsigned"
    # a new stream more than a minute behind us is refused
    assert SignatureChecker(KEY).check(frames[0], 10**12 + 60 * 100_000 + 1) == "replayed"
    with pytest.raises(ValueError, match="32 bytes"):
        SignatureChecker(b"short")


def test_forged_frame_cannot_move_a_stream_forward():
    # pymavlink 2.4 records a stream's timestamp before checking the signature; we do not
    good = split_datagram(_packets(1, signed=True)[0])[0][0]
    forged = bytearray(good.buf)
    forged[-12:-6] = (2**47).to_bytes(6, "little")  # far future timestamp, signature now wrong
    chk = SignatureChecker(KEY)
    assert chk.check(good._replace(buf=bytes(forged)), 0) == "bad_signature"
    assert chk.check(good, 0) is None


def test_load_signing_key(tmp_path):
    raw = tmp_path / "raw.key"
    raw.write_bytes(KEY)
    hexf = tmp_path / "hex.key"
    hexf.write_text(KEY.hex() + "\n")
    phrase = tmp_path / "phrase.key"
    phrase.write_text("correct horse battery staple\n")
    assert load_signing_key(raw) == KEY == load_signing_key(hexf)
    assert load_signing_key(phrase) == hashlib.sha256(b"correct horse battery staple").digest()  # MAVProxy's
    (tmp_path / "empty.key").write_bytes(b"")
    with pytest.raises(ValueError, match="empty"):
        load_signing_key(tmp_path / "empty.key")
    with pytest.raises(ValueError, match="cannot read"):
        load_signing_key(tmp_path / "missing.key")


# ---------------------------------------------------------------------------- units
@settings(max_examples=200, deadline=None, derandomize=True)
@given(st.floats(-math.pi / 2, math.pi / 2), st.floats(-math.pi, math.pi), st.floats(-500, 50_000),
       st.floats(-200, 200), st.floats(-200, 200), st.floats(-50, 50), st.floats(-10, 10))
def test_edge_units_roundtrip(lat, lon, alt, vn, ve, vd, yaw):
    tel = tm.VehicleTelemetry(lat, lon, alt, (vn, ve, vd), yaw_rad=yaw)
    g = tm.global_position_int_fields(tel, 0, home_alt_msl_m=100.0)
    assert abs(np.radians(g[1] * 1e-7) - lat) <= np.radians(0.5e-7) + 1e-15
    assert abs(np.radians(g[2] * 1e-7) - lon) <= np.radians(0.5e-7) + 1e-15
    assert abs(g[3] / 1000 - alt) <= 0.0005 + 1e-9 and abs(g[4] / 1000 - (alt - 100.0)) <= 0.0005 + 1e-9
    assert all(abs(c / 100 - v) <= 0.005 + 1e-9 for c, v in zip(g[5:8], (vn, ve, vd)))
    assert 0 <= g[8] < 36000 and abs(math.remainder(math.radians(g[8] / 100) - yaw, 2 * math.pi)) <= math.radians(0.005) + 1e-12
    a = tm.attitude_fields(tel, 0)
    assert -math.pi <= a[3] <= math.pi and abs(math.remainder(a[3] - yaw, 2 * math.pi)) < 1e-12
    r = tm.gps_raw_int_fields(tel, 0)
    assert r[7] == min(round(math.hypot(vn, ve) * 100), 65534)
    assert (r[5], r[6], r[9]) == (65535, 65535, 255)  # unknown DOPs, satellites


def test_saturation_and_invalid():
    tel = tm.VehicleTelemetry(0.1, 0.2, 1e9, (1e4, -1e4, 0.0), yaw_rad=float("nan"))
    g = tm.global_position_int_fields(tel, 2**33, 0.0)
    assert (g[0], g[3], g[5], g[6], g[8]) == (2**33 & 0xFFFFFFFF, 2**31 - 1, 32767, -32768, 65535)
    assert tm.battery_fields(tm.VehicleTelemetry(0, 0, 0, battery_voltage_v=12.6, battery_remaining_pct=150)) == \
        (12600, 100)


def test_unix_time_from_gps_time():
    from datetime import datetime, timezone
    dt = datetime(2024, 5, 18, 12, 0, 0, tzinfo=timezone.utc)
    t = gps_seconds_from_utc(dt)
    assert tm.unix_s_from_gps(t) == dt.timestamp()
    assert tm.gps_from_unix_s(tm.unix_s_from_gps(t)) == t
    assert utc_from_gps_seconds(t).timestamp() == tm.unix_s_from_gps(t)


def test_listen_port_convention():
    assert [listen_port(i) for i in range(3)] == [5760, 5770, 5780]
    assert listen_port(2, base_port=14560) == 14580
    for bad in (-1, 1.5, True, 7000):
        with pytest.raises(ValueError):
            listen_port(bad)


# ---------------------------------------------------------------------------- params
def test_param_spec_validation():
    for kw in (dict(name="x", default=0), dict(name="A" * 17, default=0), dict(name="A", default=5, max=1),
               dict(name="A", default=float("nan")), dict(name="A", default=0, min=1, max=0)):
        with pytest.raises(ValueError):
            ParamSpec(**kw)
    with pytest.raises(ValueError, match="duplicate"):
        ParamStore([ParamSpec("A", 0), ParamSpec("A", 1)])


@settings(max_examples=200, deadline=None, derandomize=True)
@given(st.floats(allow_nan=True, allow_infinity=True, width=64))
def test_param_set_law(v):
    s = ParamStore([ParamSpec("A", 0.0, -10.0, 10.0)])
    with np.errstate(over="ignore"):
        f32 = float(np.float32(v)) if math.isfinite(v) else v
    if math.isfinite(f32) and -10.0 <= v <= 10.0:
        stored = s.set("A", v)
        assert stored == s["A"] and np.float32(stored) == np.float32(v)
        assert stored == (0.0 if np.float32(v) == 0 else v)  # exact value kept unless the same on the wire
        assert s.set("A", float(np.float32(s["A"]))) == stored  # a value read back (float32) changes nothing
    else:
        with pytest.raises(ParamError) as e:
            s.set("A", v)
        assert e.value.reason == "param_rejected" and s["A"] == 0.0


def test_param_store_mapping_index_and_replace_into():
    from vehicles.sonde import SondeParams
    from vehicles.mavlink import sonde_param_specs
    sp = SondeParams(ascent_rate_m_s=6.0)
    s = ParamStore(sonde_param_specs(sp))
    assert s["SND_ASCENT"] == 6.0 and list(s)[0] == "SND_ASCENT" and s.index("SND_P1") == 2
    assert s.name_at(len(s) - 1) == list(s)[-1]
    with pytest.raises(ParamError):
        s.name_at(len(s))
    with pytest.raises(ParamError) as e:
        s.set("NOPE", 1.0)
    assert e.value.reason == "param_unknown"
    s.set("SND_P2", 0.05)
    sp2 = s.replace_into(sp)
    assert sp2.ascent_rate_m_s == 6.0 and sp2.p2_1_s == 0.05 and sp2.wind_alt_m == sp.wind_alt_m
    assert s.replace_into(SondeParams()) == SondeParams(ascent_rate_m_s=6.0, p2_1_s=0.05)  # exact, not float32


def test_apply_uav_params_rebuilds_the_simulation_objects():
    from vehicles.mavlink.params import apply_uav_params, uav_param_specs
    from vehicles.uav import WaypointMission
    from vehicles.uav_nav import NavConfig
    wm = WaypointMission([np.array([[0.8, 0.5, 3000.0]])] * 2, speed_m_s=[100.0, 90.0])
    nav = NavConfig()
    s = ParamStore(uav_param_specs(wm, nav, 1))
    assert s["WP_SPEED"] == 90.0 and s["NAV_Q"] == nav.q_m2_s3 and s["GNSS_PSD_PR"] == nav.noise.psd_pr_m2_s
    n0, m0 = apply_uav_params(s, nav, wm, 1)
    assert n0 == nav and list(m0.speed_m_s) == [100.0, 90.0]  # unchanged store: the same simulation
    s.set("WP_SPEED", 95.0)
    s.set("GNSS_PSD_PR", 800.0)
    s.set("NAV_Q", 0.05)
    n1, m1 = apply_uav_params(s, nav, wm, 1)
    assert (n1.noise.psd_pr_m2_s, n1.q_m2_s3, list(m1.speed_m_s)) == (800.0, 0.05, [100.0, 95.0])
    s.set("WP_CLIMB_MAX", 99.0)  # >= speed: the constructor refuses, the caller vetoes
    with pytest.raises(ValueError, match="max_climb"):
        apply_uav_params(s, nav, wm, 1)
