"""The bus: schema validation, codec round trips and fuzzing, key expressions, the in-memory
transport (ordering, rejection, isolation, fault hook) and the sequence tracker."""

from __future__ import annotations

import dataclasses
import logging
import math
import zlib

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from sitl.bus import (
    MESSAGE_TYPES,
    SCHEMA_VERSION,
    BeaconMeasurement,
    BusDecodeError,
    Estimate,
    FaultControl,
    InMemoryTransport,
    IntegrityEvent,
    KeyExprError,
    LinkStats,
    Message,
    RadarMeasurement,
    SchemaError,
    SequenceTracker,
    SondeRelay,
    Truth,
    UavGroupEpoch,
    UavNav,
    decode,
    encode,
    key_for,
    key_matches,
    key_pattern,
    pack_sealed,
    parse_key,
    validate_key_expr,
)
from sitl.bus.codec import seal
from sitl.bus.schema import N_SATS_MAX, POS_MAX_M, T_GPS_MAX_S, VAR_MAX, VEL_MAX_M_S

# Deterministic, quick, and no example database written into the repo.
FAST = settings(derandomize=True, database=None, deadline=None, max_examples=150,
                suppress_health_check=[HealthCheck.too_slow])
FUZZ = settings(FAST, max_examples=200)

# ----------------------------------------------------------------------------------------
# Hand-made valid messages


def _cov(seed: int = 0) -> np.ndarray:
    a = np.random.default_rng(seed).normal(size=(6, 6))
    c = a @ a.T
    return (c + c.T) / 2


HDR = dict(t_gps_s=1_400_000_000.25, source_id="uav-3", seq=41)


def nav(**kw) -> UavNav:
    base = dict(HDR, pos_ecef_m=[4.2e6, 1.1e6, 4.6e6], vel_ecef_m_s=[10.0, -2.0, 0.5],
                cov=_cov(1), n_sats=9, fix_type=3)
    return UavNav(**{**base, **kw})


def beacon(**kw) -> BeaconMeasurement:
    base = dict(HDR, range_m=1234.5, range_rate_m_s=-3.25, var_range_m2=4.0,
                var_range_rate_m2_s2=0.01, uav_pos_ecef_m=[4.2e6, 1.1e6, 4.6e6],
                uav_vel_ecef_m_s=[10.0, -2.0, 0.5], uav_cov=_cov(2))
    return BeaconMeasurement(**{**base, **kw})


def relay(n: int = 4, **kw) -> SondeRelay:
    rng = np.random.default_rng(n)
    base = dict(HDR, source_id="rx-1", sat_ids=tuple(f"G{i + 1:02d}" for i in range(n)),
                pseudorange_m=2.1e7 + rng.uniform(0, 4e6, n),
                pseudo_doppler_m_s=rng.normal(0, 500, n), var_pseudorange_m2=np.full(n, 9.0),
                var_pseudo_doppler_m2_s2=np.full(n, 0.04),
                sat_pos_ecef_m=rng.normal(0, 1.5e7, (n, 3)),
                sat_vel_ecef_m_s=rng.normal(0, 3e3, (n, 3)),
                ground_pos_ecef_m=[4.2e6, 1.1e6, 4.6e6])
    return SondeRelay(**{**base, **kw})


def radar(**kw) -> RadarMeasurement:
    base = dict(HDR, source_id="radar-1", slant_range_m=25_000.0, az_rad=1.0, el_rad=0.3,
                var_range_m2=25.0, var_az_rad2=1e-6, var_el_rad2=1e-6, angles_valid=True,
                radar_pos_ecef_m=[4.2e6, 1.1e6, 4.6e6])
    return RadarMeasurement(**{**base, **kw})


def truth(**kw) -> Truth:
    base = dict(HDR, source_id="world", kind="sonde", pos_ecef_m=[4.2e6, 1.1e6, 4.6e6],
                vel_ecef_m_s=[1.0, 2.0, 5.0])
    return Truth(**{**base, **kw})


def estimate(**kw) -> Estimate:
    base = dict(HDR, source_id="gs", kind="beacon", pos_ecef_m=[4.2e6, 1.1e6, 4.6e6],
                vel_ecef_m_s=[0.0, 0.0, 0.0], cov=_cov(3), nis=2.5, mode="fused")
    return Estimate(**{**base, **kw})


def integrity(**kw) -> IntegrityEvent:
    base = dict(HDR, source_id="gs", channel="uav-3.beacon-7", event="step", statistic=17.5)
    return IntegrityEvent(**{**base, **kw})


def link_stats(**kw) -> LinkStats:
    base = dict(HDR, source_id="gs", link="uav-3", received=120, missing=4, duplicates=2, out_of_order=3,
                gaps=2, latency_mean_s=0.125, latency_max_s=0.75, stale=False, last_t_gps_s=1_400_000_000.0)
    return LinkStats(**{**base, **kw})


def fault_control(**kw) -> FaultControl:
    base = dict(HDR, source_id="cli", link="bus:*/uav/uav2/**", spec="loss=10% delay=100ms~20ms")
    return FaultControl(**{**base, **kw})


def uav_group(n: int = 3, **kw) -> UavGroupEpoch:
    """n UAVs: the first with every part, the second a beacon measurement only, the third its nav only."""
    rng = np.random.default_rng(n)
    parts = np.array([7, 2, 1] * n, dtype=np.int64)[:n]
    has_b, has_t = (parts & 2) != 0, (parts & 4) != 0
    nan = np.nan
    base = dict(HDR, source_id="uavs1-3", group="uavs1-3", beacon_id="b7", truth_source_id="world",
                uav_ids=tuple(str(i + 1) for i in range(n)), uav_source_ids=tuple(f"uav-{i + 1}" for i in range(n)),
                parts=parts, n_sats=np.arange(n) + 6, fix_type=np.full(n, 3),
                pos_ecef_m=np.array([4.2e6, 1.1e6, 4.6e6]) + rng.normal(0, 1e3, (n, 3)),
                vel_ecef_m_s=rng.normal(0, 20, (n, 3)), cov=np.array([_cov(10 + i) for i in range(n)]).reshape(n, 6, 6),
                range_m=np.where(has_b, rng.uniform(1e3, 5e4, n), nan),
                range_rate_m_s=np.where(has_b, rng.normal(0, 30, n), nan),
                var_range_m2=np.where(has_b, 4.0, nan), var_range_rate_m2_s2=np.where(has_b, 0.01, nan),
                truth_pos_ecef_m=np.where(has_t[:, None], rng.normal(4e6, 1e5, (n, 3)), nan),
                truth_vel_ecef_m_s=np.where(has_t[:, None], rng.normal(0, 20, (n, 3)), nan))
    return UavGroupEpoch(**{**base, **kw})


FACTORIES = {"UavNav": nav, "BeaconMeasurement": beacon, "SondeRelay": relay,
             "RadarMeasurement": radar, "Truth": truth, "Estimate": estimate,
             "IntegrityEvent": integrity, "LinkStats": link_stats, "FaultControl": fault_control,
             "UavGroupEpoch": uav_group}


def test_every_kind_has_a_factory_and_round_trips():
    assert {cls.__name__ for cls in MESSAGE_TYPES.values()} == set(FACTORIES)
    for make in FACTORIES.values():
        m = make()
        b = encode(m)
        assert decode(b) == m and type(decode(b)) is type(m)
        assert encode(decode(b)) == b


def test_messages_are_frozen_and_arrays_read_only():
    m = nav()
    with pytest.raises(dataclasses.FrozenInstanceError):
        m.seq = 3  # type: ignore[misc]
    with pytest.raises(ValueError):
        m.cov[0, 0] = 1.0
    src = np.array([1.0, 2.0, 3.0])
    t = truth(pos_ecef_m=src)
    src[0] = 99.0  # the message holds its own copy
    assert t.pos_ecef_m[0] == 1.0
    assert m != nav(seq=42) and m == nav()
    assert nav() != truth()


def test_wire_payload_is_msgpack_map_with_raw_float64_arrays():
    m = nav()
    b = encode(m)
    obj = msgpack.unpackb(b, raw=False)
    assert obj["_v"] == SCHEMA_VERSION == 3 and obj["_kind"] == "uav_nav"
    assert obj["cov"] == m.cov.astype("<f8").tobytes()
    assert set(obj) == {"_v", "_kind", "_crc"} | {s.name for s in UavNav.FIELDS}
    # the checksum: the map's last entry, CRC-32 (zlib, little-endian) of every byte before it
    assert list(obj)[-1] == "_crc" and b[-11:-4] == b"\xa4_crc\xc4\x04"
    assert obj["_crc"] == zlib.crc32(b[:-4]).to_bytes(4, "little")


def test_empty_relay_epoch_and_lost_radar_angles_are_legal():
    r = relay(0)
    assert r.n == 0 and r.sat_pos_ecef_m.shape == (0, 3)
    assert decode(encode(r)) == r
    lost = radar(angles_valid=False, az_rad=math.nan, el_rad=math.nan)
    back = decode(encode(lost))
    assert back == lost and math.isnan(back.az_rad) and not back.angles_valid
    e = estimate(nis=math.nan)
    assert decode(encode(e)) == e
    assert decode(encode(integrity(event="readmit", statistic=math.nan))).event == "readmit"


def test_producer_conventions_accepted():
    """What sitl.gnss / sitl.radio hand over: numpy str satellite ids, np.mod azimuths."""
    ids_ = np.array(["G01", "R07", "G12"])
    r = relay(3, sat_ids=ids_)
    assert r.sat_ids == ("G01", "R07", "G12") and all(type(s) is str for s in r.sat_ids)
    assert decode(encode(r)) == r
    az = float(np.mod(-1e-20, 2 * np.pi))
    assert az == 2 * math.pi  # the float np.mod gives: one full turn
    assert radar(az_rad=az).az_rad == 0.0
    m = nav(n_sats=np.int64(7), t_gps_s=np.float64(5.0), pos_ecef_m=[1, 2, 3])
    assert type(m.n_sats) is int and type(m.t_gps_s) is float and m.pos_ecef_m.dtype == np.float64


def test_singular_psd_covariance_is_legal():
    c = np.zeros((6, 6))
    c[:3, :3] = np.eye(3) * 4.0  # velocity unobserved: zero block, PSD, not PD
    assert decode(encode(nav(cov=c))) == nav(cov=c)
    v = np.array([1.0, 2.0, 3.0, 0.1, 0.2, 0.3])
    assert nav(cov=np.outer(v, v)).cov.shape == (6, 6)  # rank one


# ----------------------------------------------------------------------------------------
# Hypothesis strategies of valid messages

# valid = inside the schema's declared plausibility bounds (schema version 3)
finite = st.floats(-VEL_MAX_M_S, VEL_MAX_M_S)  # velocities, range rates, Dopplers
positive = st.floats(min_value=0.0, max_value=VAR_MAX, exclude_min=True)  # variances
coord = st.floats(-POS_MAX_M, POS_MAX_M)
ids = st.from_regex(r"[A-Za-z0-9_.\-]{1,64}", fullmatch=True)
vec3 = hnp.arrays(np.float64, 3, elements=coord)
vel3 = hnp.arrays(np.float64, 3, elements=finite)


@st.composite
def covs(draw):
    if draw(st.booleans()):
        return np.diag(draw(hnp.arrays(np.float64, 6, elements=st.floats(0, 1e12))))
    a = draw(hnp.arrays(np.float64, (6, 6), elements=st.floats(-1e3, 1e3)))
    c = a @ a.T
    return (c + c.T) / 2


def header():
    return dict(t_gps_s=st.floats(0.0, T_GPS_MAX_S), source_id=ids, seq=st.integers(0, 2**63 - 1),
                incarnation=st.integers(0, 2**63 - 1))


@st.composite
def relays(draw):
    n = draw(st.integers(0, 12))
    sats = draw(st.lists(st.from_regex(r"[GREC][0-9]{2}", fullmatch=True), min_size=n,
                         max_size=n, unique=True))
    arr = lambda shape, el: hnp.arrays(np.float64, shape, elements=el)
    return draw(st.builds(
        SondeRelay, **header(), sat_ids=st.just(tuple(sats)),
        pseudorange_m=arr(n, st.floats(0, 1e8, exclude_min=True, exclude_max=True)),
        pseudo_doppler_m_s=arr(n, finite), var_pseudorange_m2=arr(n, positive),
        var_pseudo_doppler_m2_s2=arr(n, positive), sat_pos_ecef_m=arr((n, 3), coord),
        sat_vel_ecef_m_s=arr((n, 3), finite), ground_pos_ecef_m=vec3))


@st.composite
def radars(draw):
    valid = draw(st.booleans())
    az = st.floats(0, 2 * math.pi, exclude_max=True)
    el = st.floats(-math.pi / 2, math.pi / 2)
    if not valid:
        az, el = st.one_of(st.just(math.nan), az), st.one_of(st.just(math.nan), el)
    return draw(st.builds(
        RadarMeasurement, **header(), slant_range_m=st.floats(0, 1e6, exclude_min=True),
        az_rad=az, el_rad=el, var_range_m2=positive, var_az_rad2=st.floats(0, 100, exclude_min=True),
        var_el_rad2=st.floats(0, 100, exclude_min=True), angles_valid=st.just(valid), radar_pos_ecef_m=vec3))


kinds = st.sampled_from(["uav", "beacon", "sonde"])
tokens = st.from_regex(r"[A-Za-z0-9_.\-]{1,20}", fullmatch=True)
messages = st.one_of(
    st.builds(UavNav, **header(), pos_ecef_m=vec3, vel_ecef_m_s=vel3, cov=covs(),
              n_sats=st.integers(0, N_SATS_MAX), fix_type=st.integers(0, 6)),
    st.builds(BeaconMeasurement, **header(), range_m=st.floats(0, POS_MAX_M, exclude_min=True),
              range_rate_m_s=finite, var_range_m2=positive, var_range_rate_m2_s2=positive, uav_pos_ecef_m=vec3,
              uav_vel_ecef_m_s=vel3, uav_cov=covs()),
    relays(),
    radars(),
    st.builds(Truth, **header(), kind=kinds, pos_ecef_m=vec3, vel_ecef_m_s=vel3),
    st.builds(Estimate, **header(), kind=kinds, pos_ecef_m=vec3, vel_ecef_m_s=vel3,
              cov=covs(), nis=st.one_of(st.just(math.nan), st.floats(0, 1e9)), mode=tokens),
    st.builds(IntegrityEvent, **header(), channel=tokens, event=tokens,
              statistic=st.floats(allow_infinity=False)),
    st.builds(LinkStats, **header(), link=tokens, received=st.integers(0, 2**40), missing=st.integers(0, 2**40),
              duplicates=st.integers(0, 2**40), out_of_order=st.integers(0, 2**40), gaps=st.integers(0, 2**40),
              restarts=st.integers(0, 2**40), source_incarnation=st.integers(0, 2**63 - 1),
              rejected_future=st.integers(0, 2**40), rejected_stale=st.integers(0, 2**40),
              latency_mean_s=st.one_of(st.just(math.nan), st.floats(-T_GPS_MAX_S, T_GPS_MAX_S)),
              latency_max_s=st.one_of(st.just(math.nan), st.floats(-T_GPS_MAX_S, T_GPS_MAX_S)),
              stale=st.booleans(), last_t_gps_s=st.one_of(st.just(math.nan), st.floats(0, T_GPS_MAX_S))),
    st.builds(FaultControl, **header(), link=st.text(st.characters(min_codepoint=33, max_codepoint=126), min_size=1,
                                                     max_size=30),
              spec=st.text(st.characters(min_codepoint=32, max_codepoint=126), max_size=40)),
)


@pytest.mark.slow
@FAST
@given(messages)
def test_round_trip_property(m):
    b = encode(m)
    back = decode(b)
    assert type(back) is type(m) and back == m
    assert encode(back) == b  # bit-exact, NaNs included


# ----------------------------------------------------------------------------------------
# Fuzzing: any byte string -> a valid message or BusDecodeError, never anything else


def decode_or_reject(payload: bytes) -> Message | None:
    try:
        m = decode(payload)
    except BusDecodeError as e:
        assert e.reason and "\n" not in str(e)
        return None
    assert isinstance(m, Message)
    assert decode(encode(m)) == m
    return m


@pytest.mark.slow
@settings(FAST, max_examples=1000)
@given(st.binary(max_size=3000))
def test_fuzz_random_bytes(payload):
    decode_or_reject(payload)


@settings(FAST, max_examples=60)
@given(messages, st.data())
def test_fuzz_truncations(m, data):
    b = encode(m)
    for cut in data.draw(st.lists(st.integers(0, len(b) - 1), min_size=1, max_size=8)):
        with pytest.raises(BusDecodeError):
            decode(b[:cut])


def test_every_truncation_of_each_kind_rejected():
    for make in FACTORIES.values():
        b = encode(make())
        for cut in range(len(b)):
            with pytest.raises(BusDecodeError):
                decode(b[:cut])


@pytest.mark.slow
@settings(FAST, max_examples=150)
@given(messages, st.data())
def test_fuzz_bit_flips(m, data):
    b = bytearray(encode(m))
    for bit in data.draw(st.lists(st.integers(0, 8 * len(b) - 1), min_size=1, max_size=4)):
        b[bit // 8] ^= 1 << (bit % 8)
    decode_or_reject(bytes(b))


@settings(FAST, max_examples=100)
@given(messages, st.data())
def test_single_bit_flip_always_rejected_by_the_crc(m, data):
    """The fault layer's ``corrupt`` flips one bit: never accepted (a changed float would pass
    every other check), always counted under "crc"."""
    b = bytearray(encode(m))
    bit = data.draw(st.integers(0, 8 * len(b) - 1))
    b[bit // 8] ^= 1 << (bit % 8)
    with pytest.raises(BusDecodeError) as exc:
        decode(bytes(b))
    assert exc.value.reason == "crc"


@settings(FAST, max_examples=60)
@given(messages, st.data())
def test_burst_up_to_32_bits_always_rejected_by_the_crc(m, data):
    b = bytearray(encode(m))
    n = 8 * len(b)
    start = data.draw(st.integers(0, n - 1))
    length = data.draw(st.integers(1, min(32, n - start)))
    pattern = data.draw(st.integers(1, 2 ** length - 1) if length > 1 else st.just(1)) | 1 | (1 << (length - 1))
    for i in range(length):
        if pattern >> i & 1:
            bit = start + i
            b[bit // 8] ^= 1 << (bit % 8)
    with pytest.raises(BusDecodeError) as exc:
        decode(bytes(b))
    assert exc.value.reason == "crc"


def test_every_single_bit_flip_of_a_beacon_measurement_rejected():
    b = encode(beacon())
    reasons = set()
    for bit in range(8 * len(b)):
        c = bytearray(b)
        c[bit // 8] ^= 1 << (bit % 8)
        with pytest.raises(BusDecodeError) as exc:
            decode(bytes(c))
        reasons.add(exc.value.reason)
    assert reasons == {"crc"}


msgpack_values = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**63), 2**64 - 1) | st.floats()
    | st.text(max_size=8) | st.binary(max_size=64),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner,
                                                                max_size=4),
    max_leaves=12)


@pytest.mark.slow
@settings(FAST, max_examples=120)
@given(messages, st.data())
def test_fuzz_field_values(m, data):
    """Valid envelope, one field (or header key) replaced by an arbitrary msgpack value."""
    obj = msgpack.unpackb(encode(m), raw=False)
    name = data.draw(st.sampled_from(sorted(obj)))
    obj[name] = data.draw(msgpack_values)
    decode_or_reject(msgpack.packb(obj, use_bin_type=True))  # the checksum rejects it
    if name != "_crc":
        decode_or_reject(pack_sealed(obj))  # the layers after the checksum


@FUZZ
@given(msgpack_values)
def test_fuzz_msgpack_structures(value):
    decode_or_reject(msgpack.packb(value, use_bin_type=True))
    if isinstance(value, (dict, list)):
        decode_or_reject(pack_sealed(value))


def test_decode_non_bytes_raises_bus_decode_error():
    for bad in ("text", None, 3, [1, 2]):
        with pytest.raises(BusDecodeError, match="payload: not bytes"):
            decode(bad)  # type: ignore[arg-type]


# ----------------------------------------------------------------------------------------
# Every validation rule, in the constructor and on the wire, names its field


def wire_with(m: Message, drop: tuple[str, ...] = (), **overrides) -> bytes:
    obj = msgpack.unpackb(encode(m), raw=False)
    for k in drop:
        del obj[k]
    for k, v in overrides.items():
        if isinstance(v, np.ndarray):
            v = v.astype("<f8").tobytes()
        elif isinstance(v, tuple):
            v = list(v)
        obj[k] = v
    return pack_sealed(obj)  # a valid checksum: the rule after it is what is tested


NAN, INF = math.nan, math.inf
asym = _cov(1).copy()
asym[0, 1] += 1e-3
negdiag = np.eye(6)
negdiag[2, 2] = -1e-6
indefinite = np.eye(6)
indefinite[0, 1] = indefinite[1, 0] = 2.0  # eigenvalues 3, -1
pos_nan = np.array([1.0, NAN, 3.0])
pos_inf = np.array([1.0, 2.0, INF])

RULES = [  # (factory, overrides, field named in the error)
    (nav, dict(t_gps_s=NAN), "UavNav.t_gps_s"),
    (nav, dict(t_gps_s=INF), "UavNav.t_gps_s"),
    (nav, dict(t_gps_s="1.0"), "UavNav.t_gps_s"),
    (nav, dict(source_id=""), "UavNav.source_id"),
    (nav, dict(source_id="x" * 65), "UavNav.source_id"),
    (nav, dict(source_id="uav 3"), "UavNav.source_id"),
    (nav, dict(source_id="uav/3"), "UavNav.source_id"),
    (nav, dict(source_id=3), "UavNav.source_id"),
    (nav, dict(seq=-1), "UavNav.seq"),
    (nav, dict(seq=2**63), "UavNav.seq"),
    (nav, dict(seq=1.0), "UavNav.seq"),
    (nav, dict(seq=True), "UavNav.seq"),
    (nav, dict(pos_ecef_m=pos_nan), "UavNav.pos_ecef_m"),
    (nav, dict(vel_ecef_m_s=pos_inf), "UavNav.vel_ecef_m_s"),
    (nav, dict(pos_ecef_m=np.zeros(4)), "UavNav.pos_ecef_m"),
    (nav, dict(cov=asym), "UavNav.cov"),
    (nav, dict(cov=negdiag), "UavNav.cov"),
    (nav, dict(cov=indefinite), "UavNav.cov"),
    (nav, dict(cov=np.eye(5)), "UavNav.cov"),
    (nav, dict(n_sats=-1), "UavNav.n_sats"),
    (nav, dict(fix_type=7), "UavNav.fix_type"),
    (nav, dict(fix_type=-1), "UavNav.fix_type"),
    (nav, dict(fix_type=3.0), "UavNav.fix_type"),
    (beacon, dict(range_m=0.0), "BeaconMeasurement.range_m"),
    (beacon, dict(range_m=-5.0), "BeaconMeasurement.range_m"),
    (beacon, dict(range_rate_m_s=NAN), "BeaconMeasurement.range_rate_m_s"),
    (beacon, dict(var_range_m2=0.0), "BeaconMeasurement.var_range_m2"),
    (beacon, dict(var_range_rate_m2_s2=-1.0), "BeaconMeasurement.var_range_rate_m2_s2"),
    (beacon, dict(var_range_rate_m2_s2=INF), "BeaconMeasurement.var_range_rate_m2_s2"),
    (beacon, dict(uav_pos_ecef_m=pos_nan), "BeaconMeasurement.uav_pos_ecef_m"),
    (beacon, dict(uav_vel_ecef_m_s=pos_inf), "BeaconMeasurement.uav_vel_ecef_m_s"),
    (beacon, dict(uav_cov=asym), "BeaconMeasurement.uav_cov"),
    (beacon, dict(uav_cov=indefinite), "BeaconMeasurement.uav_cov"),
    (relay, dict(pseudorange_m=np.array([2e7, 0.0, 2e7, 2e7])), "SondeRelay.pseudorange_m"),
    (relay, dict(pseudorange_m=np.array([2e7, 1e8, 2e7, 2e7])), "SondeRelay.pseudorange_m"),
    (relay, dict(pseudorange_m=np.array([2e7, NAN, 2e7, 2e7])), "SondeRelay.pseudorange_m"),
    (relay, dict(pseudorange_m=np.full(3, 2e7)), "SondeRelay.pseudorange_m"),
    (relay, dict(pseudo_doppler_m_s=np.array([0.0, INF, 0.0, 0.0])),
     "SondeRelay.pseudo_doppler_m_s"),
    (relay, dict(var_pseudorange_m2=np.array([1.0, 0.0, 1.0, 1.0])),
     "SondeRelay.var_pseudorange_m2"),
    (relay, dict(var_pseudo_doppler_m2_s2=-np.ones(4)), "SondeRelay.var_pseudo_doppler_m2_s2"),
    (relay, dict(sat_pos_ecef_m=np.zeros((4, 2))), "SondeRelay.sat_pos_ecef_m"),
    (relay, dict(sat_vel_ecef_m_s=np.zeros((3, 3))), "SondeRelay.sat_vel_ecef_m_s"),
    (relay, dict(ground_pos_ecef_m=pos_nan), "SondeRelay.ground_pos_ecef_m"),
    (relay, dict(sat_ids=("G01", "G01", "G03", "G04")), "SondeRelay.sat_ids"),
    (relay, dict(sat_ids=("G01", "G 2", "G03", "G04")), "SondeRelay.sat_ids"),
    (relay, dict(sat_ids=("G01", "", "G03", "G04")), "SondeRelay.sat_ids"),
    (relay, dict(sat_ids=("G01", 2, "G03", "G04")), "SondeRelay.sat_ids"),
    (relay, dict(sat_ids="G01"), "SondeRelay.sat_ids"),
    (radar, dict(slant_range_m=0.0), "RadarMeasurement.slant_range_m"),
    (radar, dict(slant_range_m=1e6 + 1), "RadarMeasurement.slant_range_m"),
    (radar, dict(slant_range_m=NAN, angles_valid=False), "RadarMeasurement.slant_range_m"),
    (radar, dict(az_rad=2 * math.pi + 1e-9), "RadarMeasurement.az_rad"),
    (radar, dict(az_rad=-0.1), "RadarMeasurement.az_rad"),
    (radar, dict(az_rad=NAN), "RadarMeasurement.az_rad"),
    (radar, dict(az_rad=INF, angles_valid=False), "RadarMeasurement.az_rad"),
    (radar, dict(az_rad=7.0, angles_valid=False), "RadarMeasurement.az_rad"),
    (radar, dict(el_rad=1.6), "RadarMeasurement.el_rad"),
    (radar, dict(el_rad=NAN), "RadarMeasurement.el_rad"),
    (radar, dict(var_range_m2=0.0), "RadarMeasurement.var_range_m2"),
    (radar, dict(var_az_rad2=0.0), "RadarMeasurement.var_az_rad2"),
    (radar, dict(var_el_rad2=-1.0), "RadarMeasurement.var_el_rad2"),
    (radar, dict(angles_valid=1), "RadarMeasurement.angles_valid"),
    (radar, dict(radar_pos_ecef_m=pos_inf), "RadarMeasurement.radar_pos_ecef_m"),
    (truth, dict(kind="car"), "Truth.kind"),
    (truth, dict(pos_ecef_m=pos_nan), "Truth.pos_ecef_m"),
    (truth, dict(vel_ecef_m_s=pos_inf), "Truth.vel_ecef_m_s"),
    (estimate, dict(kind="uav/3"), "Estimate.kind"),
    (estimate, dict(cov=asym), "Estimate.cov"),
    (estimate, dict(cov=negdiag), "Estimate.cov"),
    (estimate, dict(nis=-1.0), "Estimate.nis"),
    (estimate, dict(nis=INF), "Estimate.nis"),
    (estimate, dict(mode=""), "Estimate.mode"),
    (estimate, dict(mode="radar only"), "Estimate.mode"),
    (estimate, dict(pos_ecef_m=pos_nan), "Estimate.pos_ecef_m"),
    (integrity, dict(channel="a/b"), "IntegrityEvent.channel"),
    (integrity, dict(event=""), "IntegrityEvent.event"),
    (integrity, dict(statistic=INF), "IntegrityEvent.statistic"),
    (integrity, dict(statistic="big"), "IntegrityEvent.statistic"),
    # plausibility (schema version 3): finite but physically absurd values
    (nav, dict(t_gps_s=-1.0), "UavNav.t_gps_s: out of range"),
    (nav, dict(t_gps_s=T_GPS_MAX_S * 1.0001), "UavNav.t_gps_s: out of range"),
    (nav, dict(incarnation=-1), "UavNav.incarnation: out of range"),
    (nav, dict(incarnation=2**63), "UavNav.incarnation: out of range"),
    (nav, dict(pos_ecef_m=np.array([4.2e6, 1.1e6, 1.0001 * POS_MAX_M])), "UavNav.pos_ecef_m: out of range"),
    (nav, dict(vel_ecef_m_s=np.array([-1.0001 * VEL_MAX_M_S, 0.0, 0.0])), "UavNav.vel_ecef_m_s: out of range"),
    (nav, dict(cov=np.eye(6) * 1.0001 * VAR_MAX), "UavNav.cov: out of range"),
    (nav, dict(n_sats=N_SATS_MAX + 1), "UavNav.n_sats: out of range"),
    (beacon, dict(range_m=1.0001 * POS_MAX_M), "BeaconMeasurement.range_m: out of range"),
    (beacon, dict(range_rate_m_s=-1.0001 * VEL_MAX_M_S), "BeaconMeasurement.range_rate_m_s: out of range"),
    (beacon, dict(var_range_m2=1e300), "BeaconMeasurement.var_range_m2: out of range"),
    (beacon, dict(uav_pos_ecef_m=np.array([1e300, 0.0, 0.0])), "BeaconMeasurement.uav_pos_ecef_m: out of range"),
    (beacon, dict(uav_cov=np.diag([1e17, 1, 1, 1, 1, 1.0])), "BeaconMeasurement.uav_cov: out of range"),
    (relay, dict(sat_pos_ecef_m=np.full((4, 3), 2 * POS_MAX_M)), "SondeRelay.sat_pos_ecef_m: out of range"),
    (relay, dict(pseudo_doppler_m_s=np.array([0.0, 3e4, 0.0, 0.0])), "SondeRelay.pseudo_doppler_m_s: out of range"),
    (relay, dict(var_pseudorange_m2=np.full(4, 1e20)), "SondeRelay.var_pseudorange_m2: out of range"),
    (radar, dict(var_az_rad2=1e3), "RadarMeasurement.var_az_rad2: out of range"),
    (radar, dict(radar_pos_ecef_m=np.array([0.0, 0.0, -2e8])), "RadarMeasurement.radar_pos_ecef_m: out of range"),
    (truth, dict(t_gps_s=1e12), "Truth.t_gps_s: out of range"),
    (estimate, dict(pos_ecef_m=np.array([3.1e8, 0.0, 0.0])), "Estimate.pos_ecef_m: out of range"),
    (estimate, dict(vel_ecef_m_s=np.array([0.0, 1e6, 0.0])), "Estimate.vel_ecef_m_s: out of range"),
    (link_stats, dict(last_t_gps_s=-5.0), "LinkStats.last_t_gps_s: out of range"),
    (link_stats, dict(restarts=-1), "LinkStats.restarts"),
]


@pytest.mark.parametrize("make, overrides, where", RULES,
                         ids=[f"{w}-{i}" for i, (_, _, w) in enumerate(RULES)])
def test_validation_rule_constructor_and_wire(make, overrides, where):
    with pytest.raises(SchemaError) as exc:
        dataclasses.replace(make(), **overrides)
    assert where in str(exc.value) and exc.value.reason.startswith(where)
    with pytest.raises(BusDecodeError) as exc:
        decode(wire_with(make(), **overrides))
    assert where in str(exc.value) and exc.value.reason.startswith(where)
    assert "\n" not in str(exc.value)


def test_relay_with_more_satellites_than_the_schema_allows_is_rejected_built_and_on_the_wire():
    n = N_SATS_MAX + 1
    ok = relay(N_SATS_MAX)
    assert decode(encode(ok)) == ok  # the largest legal relay epoch fits under the payload bound
    wire = msgpack.unpackb(encode(ok), raw=False)
    wire["sat_ids"] = [f"G{i:03d}" for i in range(n)]
    for f in ("pseudorange_m", "pseudo_doppler_m_s", "var_pseudorange_m2", "var_pseudo_doppler_m2_s2"):
        wire[f] = wire[f] + wire[f][:8]
    for f in ("sat_pos_ecef_m", "sat_vel_ecef_m_s"):
        wire[f] = wire[f] + wire[f][:24]
    with pytest.raises(BusDecodeError) as exc:
        decode(pack_sealed(wire))
    assert exc.value.reason == "SondeRelay.sat_ids: more than 256 satellites"


WIRE_RULES = [  # (payload, text of the error)
    (wire_with(nav(), drop=("_v",)), "header._v: missing schema version"),
    (wire_with(nav(), _v=1), "header._v: unsupported schema version"),
    (msgpack.packb(msgpack.unpackb(encode(nav())), use_bin_type=True)[:-4] + b"\0\0\0\0", "crc"),
    (wire_with(nav(), _v="1"), "header._v: schema version not an int"),
    (wire_with(nav(), drop=("_kind",)), "header._kind"),
    (wire_with(nav(), _kind="nav_v9"), "header._kind: unknown message kind"),
    (wire_with(nav(), drop=("cov",)), "UavNav.cov: missing"),
    (wire_with(nav(), extra=1.0), "UavNav: unexpected field"),
    (wire_with(nav(), pos_ecef_m=b"\x00" * 16), "UavNav.pos_ecef_m: wrong size"),
    (wire_with(nav(), pos_ecef_m=[1.0, 2.0, 3.0]), "UavNav.pos_ecef_m: expected bin"),
    (wire_with(nav(), t_gps_s=1), "UavNav.t_gps_s: expected float"),
    (wire_with(nav(), n_sats=9.0), "UavNav.n_sats: expected int"),
    (wire_with(radar(), angles_valid=1), "RadarMeasurement.angles_valid: expected bool"),
    (wire_with(relay(), sat_ids="G01"), "SondeRelay.sat_ids: expected array of str"),
    (wire_with(relay(), sat_ids=["G01", "G02"]), "SondeRelay.pseudorange_m: wrong size"),
    (pack_sealed([1, "uav_nav"]), "payload: not a map"),
    (msgpack.packb([1, "uav_nav"]), "crc"),
    (encode(nav()) + b"\x00", "crc"),
    (encode(nav())[:-11] + b"\x00" + encode(nav())[-11:], "crc"),
    (seal(msgpack.packb({k: v for k, v in msgpack.unpackb(encode(nav())).items() if k != "_crc"})
          + b"\xa4_crc\xc4\x04\0\0\0\0"), "payload: trailing bytes"),
    (b"", "payload: empty"),
    (b"\xc1", "crc"),
    (seal(b"\xc1\xa4_crc\xc4\x04\0\0\0\0"), "payload: not msgpack"),
    (seal(b"\x82\xa1v\xa4_crc\xc4\x04\0\0\0\0"), "payload: not msgpack"),
    (b"\x00" * (1 << 20 + 1), "payload: too large"),
]


@pytest.mark.parametrize("payload, text", WIRE_RULES, ids=[t for _, t in WIRE_RULES])
def test_wire_rule(payload, text):
    with pytest.raises(BusDecodeError) as exc:
        decode(payload)
    assert text in str(exc.value)


def test_rejection_reasons_carry_no_values():
    """Reasons key the rejection counters: bounded, free of payload-controlled text."""
    reasons = set()
    for i in range(50):
        for p in (wire_with(nav(), **{f"junk{i}": 1}), wire_with(nav(), _kind=f"k{i}"),
                  wire_with(nav(), fix_type=7 + i)):
            try:
                decode(p)
            except BusDecodeError as e:
                reasons.add(e.reason)
    assert reasons == {"UavNav: unexpected field", "header._kind: unknown message kind",
                       "UavNav.fix_type: out of range 0..6"}


# ----------------------------------------------------------------------------------------
# Keys


def test_key_builders_and_parser():
    cases = [
        (nav(), dict(uav=3), "r1/uav/3/nav", {"uav": "3"}),
        (beacon(), dict(uav="3", beacon="b7"), "r1/uav/3/beacon/b7", {"uav": "3", "beacon": "b7"}),
        (relay(), dict(sonde="s1"), "r1/sonde/s1/relay", {"sonde": "s1"}),
        (radar(), dict(radar=1, sonde="s1"), "r1/radar/1/sonde/s1", {"radar": "1", "sonde": "s1"}),
        (truth(), dict(id="s1"), "r1/truth/sonde/s1", {"kind": "sonde", "id": "s1"}),
        (estimate(), dict(id="b7"), "r1/gs/estimate/beacon/b7", {"kind": "beacon", "id": "b7"}),
        (integrity(), {}, "r1/gs/integrity/uav-3.beacon-7", {"channel": "uav-3.beacon-7"}),
    ]
    for m, ids_, key, parsed in cases:
        assert key_for("r1", m, **ids_) == key
        assert parse_key(key) == ("r1", type(m), parsed)
        assert key_matches(key_pattern("r1", type(m)), key)
        assert not key_matches(key_pattern("r2", type(m)), key)
    assert key_pattern("r1", BeaconMeasurement, uav=3) == "r1/uav/3/beacon/*"
    assert key_pattern("r1", Truth) == "r1/truth/*/*"
    assert parse_key("r1/uav/3/unknown") is None and parse_key("nokey") is None


@pytest.mark.parametrize("call, text", [
    (lambda: key_for("r1", nav()), "missing id 'uav'"),
    (lambda: key_for("r1", nav(), uav=3, beacon=2), "unexpected ids"),
    (lambda: key_for("r1", nav(), uav="a/b"), "key id uav"),
    (lambda: key_for("r1", nav(), uav="*"), "key id uav"),
    (lambda: key_for("run 1", nav(), uav=3), "run_id"),
    (lambda: key_for("r1", truth(), id="s1", kind="uav"), "contradicts"),
    (lambda: key_for("r1", Truth, id="s1", kind="car"), "key id kind"),
])
def test_key_builder_errors(call, text):
    with pytest.raises(ValueError, match=text):
        call()


# Zenoh's key-expression documentation (RFC "Key Expressions" and the manual's
# "Abstractions" page): `*` is exactly one chunk ([^/]+), `**` any number (including 0),
# verbatim `@` chunks are only matched by themselves. Keys here are concrete, so "includes"
# and "intersects" coincide.
KEY_TABLE = [
    ("a/*/b", "a/c/b", True),
    ("a/*/b", "a/hi/b", True),
    ("a/*/b", "a/hi/there/b", False),
    ("a/*/b", "a/b", False),  # * is one non-empty chunk
    ("a/*/b", "a/c/c", False),
    ("a/**/b", "a/b", True),  # ** may be zero chunks
    ("a/**/b", "a/c/b", True),
    ("a/**/b", "a/c/d/b", True),
    ("a/**/b", "a/b/b", True),
    ("a/**/b", "a/b/c", False),
    ("a/**/b", "b/a/b", False),
    ("a/**", "a", True),
    ("a/**", "a/b/c", True),
    ("a/**", "ab/c", False),
    ("**/b", "b", True),
    ("**/b", "a/c/b", True),
    ("**", "a", True),
    ("**", "a/b/c/d", True),
    ("*", "a", True),
    ("*", "a/b", False),
    ("*/*/*", "a/b/c", True),
    ("*/*/*", "a/b", False),
    ("*/a/b", "x/a/b", True),
    ("a/*/**", "a", False),
    ("a/*/**", "a/b", True),
    ("a/*/**", "a/b/c/d", True),
    ("a/**/c/**/b", "a/c/b", True),
    ("a/**/c/**/b", "a/x/c/y/z/b", True),
    ("a/**/c/**/b", "a/x/y/b", False),
    ("organizationA/building8/room275/*/temperature",
     "organizationA/building8/room275/sensor3/temperature", True),
    ("organizationA/building8/room275/*/temperature",
     "organizationA/building8/room275/sensor3/humidity", False),
    ("robot/sensor/*", "robot/sensor/temp", True),
    ("robot/**", "robot/sensor/temp", True),
    ("my-api/@v1/**", "my-api/@v1/x", True),  # verbatim chunks
    ("my-api/@v2/**", "my-api/@v1/x", False),
    ("my-api/*/x", "my-api/@v1/x", False),
    ("my-api/**", "my-api/@v1/x", False),
    ("**", "@a/b", False),
    ("a/**/@x", "a/@x", True),
    ("a/**/@x", "a/b/@x", True),
    ("r1/uav/*/beacon/*", "r1/uav/3/beacon/b7", True),
    ("r1/uav/*/beacon/*", "r1/uav/3/nav", False),
    ("r1/**", "r2/uav/3/nav", False),
    ("*/truth/**", "r1/truth/uav/3", True),
    ("r1/gs/**", "r1/gs/estimate/sonde/s1", True),
]


@pytest.mark.parametrize("expr, key, expected", KEY_TABLE)
def test_key_matches_table(expr, key, expected):
    assert key_matches(expr, key) is expected


@pytest.mark.parametrize("expr", ["", "/a", "a/", "a//b", "a/b*", "a/*b", "a/***", "a/**/**",
                                  "a/**/*", "a/?", "a/#", "a/$*", "a/x$*y"])
def test_invalid_key_expressions(expr):
    with pytest.raises(KeyExprError):
        validate_key_expr(expr)


def test_key_table_agrees_with_zenoh():
    zenoh = pytest.importorskip("zenoh")
    for expr, key, expected in KEY_TABLE:
        assert zenoh.KeyExpr(expr).intersects(zenoh.KeyExpr(key)) is expected, (expr, key)
    for expr in ["/a", "a/", "a//b", "a/b*", "a/**/**", "a/**/*", "a/?", "a/#"]:
        with pytest.raises(zenoh.ZError):
            zenoh.KeyExpr(expr)


chunk_pats = st.lists(st.sampled_from(["a", "b", "@v", "*", "**"]), min_size=1, max_size=5)
chunk_keys = st.lists(st.sampled_from(["a", "b", "@v"]), min_size=1, max_size=5)


@FAST
@given(chunk_pats, chunk_keys)
def test_key_matches_agrees_with_zenoh_property(pats, keys):
    zenoh = pytest.importorskip("zenoh")
    expr = zenoh.KeyExpr.autocanonize("/".join(pats))
    key = "/".join(keys)
    assert key_matches(str(expr), key) is expr.intersects(zenoh.KeyExpr(key))


# ----------------------------------------------------------------------------------------
# In-memory transport


class Recorder:
    def __init__(self):
        self.got: list[tuple[str, Message]] = []

    def __call__(self, key, msg):
        self.got.append((key, msg))

    @property
    def seqs(self):
        return [m.seq for _, m in self.got]


def test_queued_delivery_order_and_filtering():
    bus = InMemoryTransport()
    everything, navs, b3 = Recorder(), Recorder(), Recorder()
    bus.subscribe("r1/**", everything)
    bus.subscribe(key_pattern("r1", UavNav), navs)
    bus.subscribe("r1/uav/3/beacon/*", b3)
    bus.publish(key_for("r1", nav(seq=1), uav=3), nav(seq=1))
    bus.publish(key_for("r1", beacon(seq=2), uav=3, beacon=7), beacon(seq=2))
    bus.publish(key_for("r1", nav(seq=3), uav=4), nav(seq=3))
    bus.publish(key_for("r1", beacon(seq=4), uav=4, beacon=7), beacon(seq=4))
    bus.publish("r2/uav/3/nav", nav(seq=5))
    assert everything.got == [] and bus.pending == 5  # queued until drained
    assert bus.drain() == 5
    assert everything.seqs == [1, 2, 3, 4]  # same time: publish order
    assert navs.seqs == [1, 3] and b3.seqs == [2]
    assert [k for k, _ in everything.got] == ["r1/uav/3/nav", "r1/uav/3/beacon/7",
                                              "r1/uav/4/nav", "r1/uav/4/beacon/7"]
    assert bus.stats.published == 5 and bus.stats.total.delivered == 4  # r2: no subscriber


def test_drain_until_delivers_in_time_order():
    bus = InMemoryTransport()
    rec = Recorder()
    bus.subscribe("r/**", rec)
    t0 = 1000.0
    for seq, dt in enumerate([0.2, 0.0, 0.1, 0.2, 0.05]):
        bus.publish(f"r/uav/{seq}/nav", nav(t_gps_s=t0 + dt, seq=seq))
    assert bus.drain(t0 + 0.1) == 3
    assert rec.seqs == [1, 4, 2]
    assert bus.now_s == t0 + 0.2  # the clock: latest publication or drain time
    bus.drain(t0 + 1)
    assert rec.seqs == [1, 4, 2, 0, 3]  # ties (t0+0.2) in publish order


def test_synchronous_mode_and_reentrant_publish():
    bus = InMemoryTransport(synchronous=True)
    rec = Recorder()
    bus.subscribe("r/**", rec)

    def echo(key, msg):
        if key == "r/uav/1/nav":  # a consumer publishing from its callback
            bus.publish("r/gs/estimate/uav/1", estimate(seq=100, t_gps_s=msg.t_gps_s))
            assert rec.seqs[-1] == msg.seq  # not delivered re-entrantly

    bus.subscribe("r/uav/*/nav", echo)
    bus.publish("r/uav/1/nav", nav(seq=1))
    assert rec.seqs == [1, 100]  # delivered before publish returned, echo after its cause
    bus.publish("r/uav/2/nav", nav(seq=2))
    assert rec.seqs == [1, 100, 2]


def test_malformed_payload_rejected_counted_logged_once(caplog):
    bus = InMemoryTransport()
    rec, other = Recorder(), Recorder()
    sub = bus.subscribe("r/**", rec)
    sub2 = bus.subscribe("r/uav/*/nav", other)
    caplog.set_level(logging.WARNING, logger="sitl.bus")
    for _ in range(3):
        bus.publish_raw("r/uav/1/nav", b"\xc1garbage")
    bus.publish_raw("r/uav/1/nav", wire_with(nav(), fix_type=9))
    bus.publish("r/uav/1/nav", nav(seq=7))
    bus.drain()  # never raises
    assert rec.seqs == [7] and other.seqs == [7]
    stats = bus.stats.total
    assert stats.rejected == {"crc": 3, "UavNav.fix_type: out of range 0..6": 1}
    assert stats.delivered == 1 and stats.rejected_total == 4
    assert sub.stats.rejected == stats.rejected and sub2.stats.rejected_total == 4
    assert bus.stats.per_subscription[sub.id] is sub.stats
    assert sub.stats.bytes == 3 * 8 + len(wire_with(nav(), fix_type=9)) + len(encode(nav(seq=7)))
    logged = [r.getMessage() for r in caplog.records]
    assert sum("crc" in t for t in logged) == 1  # once per reason
    assert sum("fix_type" in t for t in logged) == 1
    # the transport keeps working
    bus.publish("r/uav/1/nav", nav(seq=8))
    bus.drain()
    assert rec.seqs == [7, 8]


def test_rejection_log_is_rate_limited(caplog):
    bus = InMemoryTransport()
    bus.subscribe("r/**", Recorder())
    caplog.set_level(logging.WARNING, logger="sitl.bus")
    for _ in range(150):
        bus.publish_raw("r/x", b"")
    bus.drain()
    assert bus.stats.total.rejected["payload: empty"] == 150
    assert len(caplog.records) == 3  # 1st, 10th, 100th


def test_callback_exception_isolated(caplog):
    bus = InMemoryTransport()
    calls, rec = [], Recorder()

    def broken(key, msg):
        calls.append(msg.seq)
        raise RuntimeError("consumer bug")

    bad = bus.subscribe("r/**", broken)
    good = bus.subscribe("r/**", rec)
    caplog.set_level(logging.ERROR, logger="sitl.bus")
    for seq in range(3):
        bus.publish("r/uav/1/nav", nav(seq=seq))
    bus.drain()
    assert calls == [0, 1, 2] and rec.seqs == [0, 1, 2]
    assert bad.stats.callback_errors == 3 and good.stats.callback_errors == 0
    assert bus.stats.total.callback_errors == 3
    assert bad.stats.delivered == 3 and bus.stats.total.delivered == 3
    assert len(caplog.records) == 1 and "consumer bug" in caplog.records[0].getMessage()


def test_subscription_and_transport_close():
    bus = InMemoryTransport()
    rec = Recorder()
    sub = bus.subscribe("r/**", rec)

    closer = bus.subscribe("r/**", lambda k, m: sub.close())  # closes the other mid-stream
    bus.publish("r/uav/1/nav", nav(seq=1))
    bus.drain()
    assert rec.seqs == [1]  # `sub` came first, then `closer` closed it
    closer.close()
    bus.publish("r/uav/1/nav", nav(seq=2))
    bus.drain()
    assert rec.seqs == [1] and sub.closed
    sub.close()  # idempotent
    bus.close()
    with pytest.raises(RuntimeError):
        bus.publish("r/uav/1/nav", nav())
    with pytest.raises(RuntimeError):
        bus.subscribe("r/**", rec)


def test_bad_keys_raise_to_the_caller():
    bus = InMemoryTransport()
    with pytest.raises(KeyExprError):
        bus.publish("r/uav/*/nav", nav())
    with pytest.raises(KeyExprError):
        bus.publish("r//nav", nav())
    with pytest.raises(KeyExprError):
        bus.subscribe("r/**/**", Recorder())
    with pytest.raises(TypeError):
        bus.publish_raw("r/x", "not bytes")  # type: ignore[arg-type]


def test_fault_hook_drop_everything():
    seen = []

    def drop(key, payload, t):
        seen.append((key, t))
        return []

    bus = InMemoryTransport(faults=[drop])
    rec = Recorder()
    bus.subscribe("r/**", rec)
    for seq in range(5):
        bus.publish("r/uav/1/nav", nav(seq=seq, t_gps_s=10.0 + seq))
    assert bus.drain() == 0 and rec.got == []
    assert seen == [("r/uav/1/nav", 10.0 + s) for s in range(5)]
    assert bus.stats.published == 5 and bus.stats.total.delivered == 0


def test_fault_hook_duplicate_everything_and_sequence_tracker():
    bus = InMemoryTransport(faults=[lambda key, p, t: [(t, p), (t, p)]])
    tracker = SequenceTracker()
    verdicts = []
    bus.subscribe("r/**", lambda k, m: verdicts.append(tracker.update(m.source_id, m.seq)))
    for seq in range(3):
        bus.publish("r/uav/1/nav", nav(seq=seq))
    bus.drain()
    assert [v.status for v in verdicts] == ["new", "duplicate"] * 3
    assert bus.stats.total.delivered == 6
    assert tracker.counters("uav-3").duplicates == 3 and tracker.total.new == 3


def test_fault_hook_delay_chain_and_corruption():
    delay = lambda key, p, t: [(t + 0.5, p)]
    corrupt_nav = lambda key, p, t: [(t, p[:-1] if key.endswith("/nav") else p)]
    bus = InMemoryTransport(faults=[delay, delay, corrupt_nav])
    rec = Recorder()
    bus.subscribe("r/**", rec)
    bus.publish("r/uav/1/nav", nav(t_gps_s=100.0, seq=1))
    bus.publish("r/truth/sonde/s1", truth(t_gps_s=100.0, seq=2))
    assert bus.drain(100.9) == 0 and bus.next_delivery_t() == 101.0
    assert bus.drain(101.0) == 2
    assert rec.seqs == [2]  # the truncated nav was rejected
    assert bus.stats.total.rejected_total == 1


def test_fault_hook_must_return_times_and_bytes():
    bus = InMemoryTransport(faults=[lambda key, p, t: [(math.nan, p)]])
    with pytest.raises(TypeError):
        bus.publish("r/x", nav())


def test_publish_raw_uses_the_transport_clock():
    times = []
    bus = InMemoryTransport(faults=[lambda k, p, t: (times.append(t), [(t, p)])[1]])
    bus.publish("r/uav/1/nav", nav(t_gps_s=50.0))
    bus.publish_raw("r/uav/1/nav", encode(nav(t_gps_s=60.0)))
    bus.publish_raw("r/uav/1/nav", encode(nav(t_gps_s=60.0)), t_gps_s=70.0)
    assert times == [50.0, 50.0, 70.0]


# ----------------------------------------------------------------------------------------
# Sequence tracker


def test_sequence_tracker_in_order_gap_late_duplicate():
    tr = SequenceTracker()
    out = [tr.update("a", s) for s in [0, 1, 2, 5, 3, 3, 6, 5, 4]]
    assert [(r.status, r.gap) for r in out] == [
        ("new", 0), ("new", 0), ("new", 0), ("new", 2), ("late", 0), ("duplicate", 0),
        ("new", 0), ("duplicate", 0), ("late", 0)]
    c = tr.counters("a")
    assert (c.received, c.new, c.duplicates, c.out_of_order, c.gaps, c.missing) == (9, 5, 2, 2,
                                                                                    1, 0)
    assert out[4].out_of_order and out[4].fresh and out[5].duplicate and not out[5].fresh


def test_sequence_tracker_sources_independent_and_totals():
    tr = SequenceTracker()
    tr.update("a", 10)
    tr.update("b", 10)  # another source: new, not a duplicate
    tr.update("a", 13)
    tr.update("b", 10)
    assert tr.counters("a").missing == 2 and tr.counters("a").duplicates == 0
    assert tr.counters("b").duplicates == 1
    assert (tr.total.received, tr.total.duplicates, tr.total.missing) == (4, 1, 2)
    assert set(tr.sources) == {"a", "b"} and tr.counters("zzz").received == 0


def test_sequence_tracker_window_and_restart():
    tr = SequenceTracker(window=8)
    for s in range(20):
        tr.update("a", s)
    assert tr.update("a", 13).status == "duplicate"  # inside the window
    assert tr.update("a", 0).status == "restart"  # far behind: the source restarted
    assert tr.update("a", 1).status == "new" and tr.update("a", 1).status == "duplicate"
    assert tr.update("a", 100).gap == 98
    assert tr.update("a", 99).status == "late"
    assert tr.counters("a").restarts == 1


# ----------------------------------------------------------------------------------------
# The fast paths (compiled covariance check, plain-value shortcuts, caches) decide as the
# reference does


def _reference_cov_verdict(c):
    from sitl.bus import schema

    saved = schema._cov_code
    schema._cov_code = None  # the numpy reference alone
    try:
        schema._check_cov("C", c)
        return "ok"
    except SchemaError as e:
        return e.reason
    finally:
        schema._cov_code = saved


def test_compiled_cov_check_agrees_with_the_reference():
    from sitl.bus import schema
    from sitl.bus._fastcheck import cov_code

    if cov_code is None:
        pytest.skip("numba not installed")
    rng = np.random.default_rng(11)
    cases = []
    for k in range(300):
        A = rng.standard_normal((6, 6)) * 10.0 ** rng.integers(-6, 7)
        kind = k % 6
        if kind == 0:
            c = A @ A.T  # positive definite
        elif kind == 1:
            c = A[:, :3] @ A[:, :3].T  # singular: legal
        elif kind == 2:
            c = A + A.T  # indefinite in general
        elif kind == 3:
            c = A @ A.T
            c[0, 1] += 1e-6 * abs(c).max()  # not symmetric
        elif kind == 4:
            c = A @ A.T
            c[2, 2] = -abs(c[2, 2]) - 1.0  # negative diagonal
        else:
            v = rng.standard_normal(6)
            c = np.outer(v, v) - 1e-12 * np.eye(6) * rng.integers(0, 2)  # rank one, maybe a hair below
        cases.append(c)
    cases += [np.zeros((6, 6)), np.eye(6), np.diag([1e300, 1e-300, 1, 1, 1, 1]),
              np.full((6, 6), 1e308), np.diag([-0.0, 0, 0, 0, 0, 0])]
    verdicts = set()
    for c in cases:
        ref = _reference_cov_verdict(c)
        code = cov_code(c)
        if code == 0:
            assert ref == "ok", (ref, c)
        try:
            schema._check_cov("C", c)
            fast = "ok"
        except SchemaError as e:
            fast = e.reason
        assert fast == ref
        verdicts.add(ref)
    assert verdicts == {"ok", "C: not symmetric", "C: negative diagonal", "C: not positive semi-definite"}


@pytest.mark.parametrize("value", [3, np.float64(3.5), np.float32(2.0), True, math.nan, math.inf, "1"])
def test_float_fields_accept_and_reject_as_before(value):
    ok = not isinstance(value, (bool, str)) and math.isfinite(float(value))
    if ok:
        m = nav(t_gps_s=value)
        assert type(m.t_gps_s) is float and m.t_gps_s == float(value)
    else:
        with pytest.raises(SchemaError, match=r"UavNav\.t_gps_s"):
            nav(t_gps_s=value)


def test_array_fields_are_read_only_copies_from_any_input():
    src = np.array([1.0, 2.0, 3.0])
    for v in (src, [1, 2, 3], np.array([1, 2, 3]), src.astype(">f8"), np.ascontiguousarray(np.eye(3)[:, 0])):
        m = nav(pos_ecef_m=v)
        assert m.pos_ecef_m.dtype == np.float64 and not m.pos_ecef_m.flags.writeable
        assert m.pos_ecef_m is not v
    m = nav(pos_ecef_m=src)
    src[0] = 99.0
    assert m.pos_ecef_m[0] == 1.0
    with pytest.raises(SchemaError, match="not finite"):
        nav(pos_ecef_m=np.array([1.0, np.nan, 3.0]))
    with pytest.raises(SchemaError, match="wrong shape"):
        nav(pos_ecef_m=np.zeros(4))


def test_parse_key_cache_hands_out_fresh_dicts():
    a = parse_key("r1/uav/3/beacon/b7")
    a[2]["uav"] = "mutated"
    assert parse_key("r1/uav/3/beacon/b7")[2] == {"uav": "3", "beacon": "b7"}
    assert parse_key("r1/nope") is None and parse_key("r1/nope") is None


def test_subscriptions_made_or_closed_after_a_key_was_delivered():
    bus = InMemoryTransport(synchronous=True)
    got = []
    key = key_for("r1", UavNav, uav=1)
    bus.publish(key, nav())  # no subscriber yet: nothing delivered, the key's (empty) match is cached
    s1 = bus.subscribe("r1/**", lambda k, m: got.append(("a", k)))
    bus.publish(key, nav())
    s2 = bus.subscribe("*/uav/*/nav", lambda k, m: got.append(("b", k)))
    bus.publish(key, nav())
    s1.close()
    bus.publish(key, nav())
    s2.close()
    bus.publish(key, nav())
    assert got == [("a", key), ("a", key), ("b", key), ("b", key)]
