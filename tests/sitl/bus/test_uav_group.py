"""The columnar bus message (sitl.bus.UavGroupEpoch): bit-exact round trip, every malformed
payload rejected with a stable reason and counted by the transport like any other kind, and its
per-UAV view equal to the messages the constructors make from the same values."""
from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest

from sitl.bus import (
    BeaconMeasurement,
    BusDecodeError,
    InMemoryTransport,
    SchemaError,
    Truth,
    UavGroupEpoch,
    UavNav,
    decode,
    encode,
    key_for,
    pack_sealed,
    parse_key,
)
from sitl.bus.schema import PART_BEACON, PART_NAV, PART_TRUTH, UAV_GROUP_MAX
from tests.sitl.bus.test_bus import uav_group


def _wire(m, **overrides) -> bytes:
    """m's payload with fields replaced by raw wire values (a valid checksum: the rule after it is tested)."""
    obj = msgpack.unpackb(encode(m), raw=False)
    obj.update(overrides)
    return pack_sealed(obj)


@pytest.mark.parametrize("n", [0, 1, 3, 17, UAV_GROUP_MAX])
def test_round_trip_is_bit_exact(n):
    m = uav_group(n)
    b = encode(m)
    d = decode(b)
    assert type(d) is UavGroupEpoch and d == m and encode(d) == b
    for f in ("pos_ecef_m", "cov", "range_m", "truth_pos_ecef_m", "parts", "n_sats"):
        assert getattr(d, f).tobytes() == getattr(m, f).tobytes(), f  # NaNs included, bit for bit
    assert d.parts.dtype == np.int64 and not d.parts.flags.writeable
    assert len(encode(uav_group(UAV_GROUP_MAX))) < 64 << 10  # under the codec's payload bound


def test_key_carries_the_group():
    m = uav_group(3)
    key = key_for("r1", m)
    assert key == "r1/uavs/uavs1-3/epoch"
    run, cls, ids = parse_key(key)
    assert (run, cls, ids) == ("r1", UavGroupEpoch, {"group": "uavs1-3"})


def test_per_uav_view_is_what_the_constructors_make():
    m = uav_group(6)  # parts 7, 2, 1, 7, 2, 1
    got = m.per_uav("r1")
    hdr = dict(t_gps_s=m.t_gps_s, seq=m.seq, incarnation=m.incarnation)
    want = []
    for j in range(6):
        uid, src, p = m.uav_ids[j], m.uav_source_ids[j], int(m.parts[j])
        if p & PART_NAV:
            want.append((key_for("r1", UavNav, uav=uid), UavNav(
                **hdr, source_id=src, pos_ecef_m=m.pos_ecef_m[j], vel_ecef_m_s=m.vel_ecef_m_s[j], cov=m.cov[j],
                n_sats=int(m.n_sats[j]), fix_type=int(m.fix_type[j]))))
        if p & PART_BEACON:
            want.append((key_for("r1", BeaconMeasurement, uav=uid, beacon="b7"), BeaconMeasurement(
                **hdr, source_id=src, range_m=float(m.range_m[j]), range_rate_m_s=float(m.range_rate_m_s[j]),
                var_range_m2=float(m.var_range_m2[j]), var_range_rate_m2_s2=float(m.var_range_rate_m2_s2[j]),
                uav_pos_ecef_m=m.pos_ecef_m[j], uav_vel_ecef_m_s=m.vel_ecef_m_s[j], uav_cov=m.cov[j])))
        if p & PART_TRUTH:
            want.append((key_for("r1", Truth, kind="uav", id=uid), Truth(
                **hdr, source_id="world", kind="uav", pos_ecef_m=m.truth_pos_ecef_m[j],
                vel_ecef_m_s=m.truth_vel_ecef_m_s[j])))
    assert [k for k, _ in got] == [k for k, _ in want]
    assert [len(got), sum(type(x) is Truth for _, x in got)] == [10, 2]
    for (_, a), (_, b) in zip(got, want):
        assert type(a) is type(b) and a == b and encode(a) == encode(b)
        for f in a.FIELDS:  # the same Python types as the constructors give
            assert type(getattr(a, f.name)) is type(getattr(b, f.name)), f.name
        assert a.__dict__.keys() == b.__dict__.keys()
    # only what is wanted is made
    beacons = m.per_uav("r1", want=lambda k: "/beacon/" in k)
    assert [k for k, _ in beacons] == [k for k, x in want if type(x) is BeaconMeasurement]


nan = math.nan


def _with(m, **cols):
    d = {f.name: getattr(m, f.name) for f in m.FIELDS}
    for k, v in cols.items():
        d[k] = v
    return d


def _set(a, j, v):
    a = np.array(a, copy=True)
    a[j] = v
    return a


M = uav_group(3)  # UAV 1: every part; UAV 2: its beacon measurement only; UAV 3: its nav only
BAD = [  # (field overrides, stable reason)
    (dict(parts=np.array([7, 2, 8])), "UavGroupEpoch.parts: out of range [0, 7]"),
    (dict(parts=np.array([7, 2, -1])), "UavGroupEpoch.parts: out of range [0, 7]"),
    (dict(parts=np.array([7.0, 2.0, 1.0])), "UavGroupEpoch.parts: expected an int array"),
    (dict(parts=np.array([7, 2])), "UavGroupEpoch.parts: wrong shape"),
    (dict(n_sats=np.array([8, 8, 257])), "UavGroupEpoch.n_sats: out of range [0, 256]"),
    (dict(fix_type=np.array([3, 7, 3])), "UavGroupEpoch.fix_type: out of range [0, 6]"),
    (dict(range_m=_set(M.range_m, 0, nan)), "UavGroupEpoch.range_m: NaN where present"),
    (dict(range_m=_set(M.range_m, 2, 5.0)), "UavGroupEpoch.range_m: a value where absent (must be NaN)"),
    (dict(range_m=_set(M.range_m, 1, -5.0)), "UavGroupEpoch.range_m: must be > 0"),
    (dict(range_m=_set(M.range_m, 1, 2e8)), "UavGroupEpoch.range_m: out of range (|x| <= 1e+08)"),
    (dict(var_range_m2=_set(M.var_range_m2, 0, 0.0)), "UavGroupEpoch.var_range_m2: must be > 0"),
    (dict(range_rate_m_s=_set(M.range_rate_m_s, 0, math.inf)), "UavGroupEpoch.range_rate_m_s: not finite"),
    (dict(truth_pos_ecef_m=_set(M.truth_pos_ecef_m, (1, 0), 1.0)),
     "UavGroupEpoch.truth_pos_ecef_m: a value where absent (must be NaN)"),
    (dict(truth_vel_ecef_m_s=_set(M.truth_vel_ecef_m_s, (0, 2), nan)),
     "UavGroupEpoch.truth_vel_ecef_m_s: NaN where present"),
    (dict(pos_ecef_m=_set(M.pos_ecef_m, (2, 1), nan)), "UavGroupEpoch.pos_ecef_m: not finite"),
    (dict(cov=_set(M.cov, (1, 0, 1), M.cov[1, 0, 1] + 1.0)), "UavGroupEpoch.cov: not symmetric"),
    (dict(cov=_set(M.cov, (2, 3, 3), -1.0)), "UavGroupEpoch.cov: negative diagonal"),
    (dict(uav_ids=("1", "2", "2")), "UavGroupEpoch.uav_ids: duplicate UAV id"),
    (dict(uav_ids=("1", "2", "x/y")), "UavGroupEpoch.uav_ids: only [A-Za-z0-9_.-] allowed"),
    (dict(uav_source_ids=("uav-1", "uav-2")), "UavGroupEpoch.uav_source_ids: not one per UAV"),
    (dict(beacon_id=""), "UavGroupEpoch.beacon_id: empty"),
]


@pytest.mark.parametrize("overrides, reason", BAD, ids=[r for _, r in BAD])
def test_malformed_is_refused_built_and_decoded_with_a_stable_reason(overrides, reason):
    with pytest.raises(SchemaError) as e:
        UavGroupEpoch(**_with(M, **overrides))
    assert e.value.reason == reason
    # the same values on the wire: the decoder says the same (a wrong shape is a wrong byte count
    # there), in one line; a bin has no dtype, so float parts are not a wire case
    if "expected an int array" in reason:
        return
    wire = {k: (v.astype("<i8" if v.dtype.kind in "iu" else "<f8").tobytes() if isinstance(v, np.ndarray)
                else list(v) if isinstance(v, tuple) else v) for k, v in overrides.items()}
    with pytest.raises(BusDecodeError) as e:
        decode(_wire(M, **wire))
    assert e.value.reason == reason.replace("wrong shape", "wrong size") and "\n" not in str(e.value)


def test_more_uavs_than_a_group_message_holds_is_refused():
    with pytest.raises(SchemaError) as e:
        uav_group(UAV_GROUP_MAX + 1)
    assert e.value.reason == f"UavGroupEpoch.uav_ids: more than {UAV_GROUP_MAX} UAVs"


@pytest.mark.parametrize("field, raw, reason", [
    ("parts", b"\x01" * 23, "UavGroupEpoch.parts: wrong size"),  # 3 int64s are 24 bytes
    ("parts", [7, 2, 1], "UavGroupEpoch.parts: expected bin (int64 bytes)"),
    ("cov", b"\0" * 8, "UavGroupEpoch.cov: wrong size"),
    ("uav_ids", ["1", 2, "3"], "UavGroupEpoch.uav_ids: expected array of str"),
])
def test_wire_types_and_sizes(field, raw, reason):
    with pytest.raises(BusDecodeError) as e:
        decode(_wire(M, **{field: raw}))
    assert e.value.reason == reason


def test_malformed_group_payloads_are_rejected_and_counted_by_the_transport():
    bus = InMemoryTransport(synchronous=True)
    got = []
    bus.subscribe("r1/uavs/*/epoch", lambda k, m: got.append(m))
    key = key_for("r1", M)
    bus.publish(key, M)
    bad = [_wire(M, parts=np.array([7, 2, 9]).astype("<i8").tobytes()),
           _wire(M, range_m=_set(M.range_m, 2, 1.0).tobytes()), encode(M)[:-1]]
    for p in bad:
        bus.publish_raw(key, p)
    assert len(got) == 1 and got[0] == M
    assert dict(bus.stats.total.rejected) == {"UavGroupEpoch.parts: out of range [0, 7]": 1,
                                              "UavGroupEpoch.range_m: a value where absent (must be NaN)": 1,
                                              "crc": 1}
    bus.close()
