"""MAVLink FTP parameter download (vehicles/mavlink/ftp.py, param_pck.py) against independent
peers: MAVProxy 1.8.75's own param.pck decoder (MAVProxy/modules/lib/param_ftp.py), its FTP
client and parameter logic (mavproxy_ftp.FTPModule, mavproxy_param.ParamState) run on a fake
MPState without a network, and real MAVLink 2 wire packets packed and parsed by pymavlink.

No sockets, no sleeps: MAVProxy's clock is replaced by a fake one (its retry timers read
``time.time()`` / ``time.monotonic()`` of its module)."""
from __future__ import annotations

import collections
import io
import math
import struct
import types

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from vehicles.mavlink import param_pck
from vehicles.mavlink.ftp import (
    DATA_LEN, ERR_EOF, ERR_FAIL, ERR_FAIL_ERRNO, ERR_FILE_NOT_FOUND, ERR_FILE_PROTECTED, ERR_INVALID_DATA_SIZE,
    ERR_INVALID_SESSION, ERR_NO_SESSIONS_AVAILABLE, ERR_UNKNOWN_COMMAND, OP_ACK, OP_BURST_READ_FILE,
    OP_CALC_FILE_CRC32, OP_CREATE_FILE, OP_LIST_DIRECTORY, OP_LIST_DIRECTORY_WITH_TIME, OP_NAK, OP_NONE,
    OP_OPEN_FILE_RO, OP_READ_FILE, OP_RENAME, OP_RESET_SESSIONS, OP_TERMINATE_SESSION, OP_TRUNCATE_FILE,
    OP_WRITE_FILE, PAYLOAD_LEN, FtpOp, FtpServer, addressed_to, advertised_capabilities,
)
from vehicles.mavlink.params import ParamSpec, ParamStore, uav_param_specs

param_ftp = pytest.importorskip("MAVProxy.modules.lib.param_ftp")
mavproxy_ftp = pytest.importorskip("MAVProxy.modules.mavproxy_ftp")
mavproxy_param = pytest.importorskip("MAVProxy.modules.mavproxy_param")
from pymavlink import mavparm  # noqa: E402

PATH = b"@PARAM/param.pck"


def f32(x: float) -> float:
    return float(np.float32(x))


# ---------------------------------------------------------------------------- parameter tables
def ardupilot_like_specs(n: int = 1000, seed: int = 1) -> ParamStore:
    """n parameters named the way ArduPilot's are (GROUP[index]_FIELD, with shared prefixes),
    synthetic values of every magnitude; about a third differ from their defaults."""
    families = [
        ("SERVO", range(1, 33), ["_MIN", "_MAX", "_TRIM", "_REVERSED", "_FUNCTION"]),
        ("RC", range(1, 17), ["_MIN", "_MAX", "_TRIM", "_REVERSED", "_DZ", "_OPTION"]),
        ("BATT", ["", "2", "3", "4", "5", "6", "7", "8", "9"],
         ["_MONITOR", "_CAPACITY", "_VOLT_PIN", "_CURR_PIN", "_VOLT_MULT", "_AMP_PERVLT", "_AMP_OFFSET",
          "_LOW_VOLT", "_CRT_VOLT", "_FS_LOW_ACT", "_ARM_VOLT", "_SERIAL_NUM"]),
        ("INS_", ["ACC", "ACC2", "ACC3", "GYR", "GYR2", "GYR3"], ["OFFS_X", "OFFS_Y", "OFFS_Z", "SCAL_X",
                                                                 "SCAL_Y", "SCAL_Z", "_ID", "_CALTEMP"]),
        ("COMPASS_", ["OFS", "OFS2", "OFS3", "DIA", "DIA2", "DIA3", "ODI", "ODI2", "ODI3", "MOT", "MOT2",
                      "MOT3"], ["_X", "_Y", "_Z"]),
        ("SERIAL", range(0, 9), ["_BAUD", "_PROTOCOL", "_OPTIONS"]),
        ("EK3_SRC", range(1, 4), ["_POSXY", "_VELXY", "_POSZ", "_VELZ", "_YAW"]),
        ("EK3_", [""], ["ENABLE", "GPS_CHECK", "IMU_MASK", "GYRO_P_NSE", "ACC_P_NSE", "GBIAS_P_NSE",
                        "ABIAS_P_NSE", "WIND_P_NSE", "VELNE_M_NSE", "VELD_M_NSE", "POSNE_M_NSE", "ALT_M_NSE",
                        "MAG_M_NSE", "EAS_M_NSE", "YAW_M_NSE", "GLITCH_RAD", "CHECK_SCALE", "ERR_THRESH"]),
        ("SR", range(0, 7), ["_RAW_SENS", "_EXT_STAT", "_RC_CHAN", "_RAW_CTRL", "_POSITION", "_EXTRA1",
                             "_EXTRA2", "_EXTRA3", "_PARAMS", "_ADSB"]),
        ("WP_", [""], ["RADIUS", "MAX_RADIUS", "LOITER_RAD", "SPEED"]),
        ("ARSPD", ["", "2"], ["_TYPE", "_USE", "_OFFSET", "_RATIO", "_PIN", "_AUTOCAL", "_TUBE_ORDER",
                              "_SKIP_CAL", "_PSI_RANGE", "_BUS"]),
        ("RLL2SRV_", [""], ["TCONST", "RMAX", "P", "I", "D", "IMAX", "FF"]),
        ("PTCH2SRV_", [""], ["TCONST", "RMAX_UP", "RMAX_DN", "RLL", "P", "I", "D", "IMAX", "FF"]),
        ("Q_", [""], ["ENABLE", "ANGLE_MAX", "TRANSITION_MS", "ASSIST_SPEED", "ASSIST_ANGLE"]),
        ("LOG_", [""], ["BITMASK", "BACKEND_TYPE", "FILE_BUFSIZE", "DISARMED", "REPLAY", "FILE_DSRMROT"]),
        ("GPS", ["", "1", "2"], ["_TYPE", "_AUTO_SWITCH", "_MIN_DGPS", "_NAVFILTER", "_GNSS_MODE", "_RATE_MS",
                                 "_POS_X", "_POS_Y", "_POS_Z", "_DELAY_MS"]),
        ("OSD", range(1, 5), ["_ENABLE", "_CHAN", "_SW_MIN", "_SW_MAX", "_TXT_RES", "_FONT", "_W_BAT_VOLT",
                              "_W_RSSI", "_W_CURRENT", "_W_BATUSED", "_W_SATS", "_W_FLTMODE", "_W_MESSAGE",
                              "_W_GSPEED", "_W_HORIZON", "_W_HOME", "_W_HEADING", "_W_THROTTLE", "_W_COMPASS",
                              "_W_WIND", "_W_ASPEED", "_W_VSPEED"]),
        ("RELAY", range(1, 7), ["_FUNCTION", "_PIN", "_DEFAULT", "_INVERTED"]),
        ("TECS_", [""], ["CLMB_MAX", "SINK_MIN", "TIME_CONST", "THR_DAMP", "INTEG_GAIN", "VERT_ACC", "HGT_OMEGA",
                         "SPD_OMEGA", "RLL2THR", "SPDWEIGHT", "PTCH_DAMP", "SINK_MAX", "LAND_ARSPD", "LAND_THR",
                         "LAND_SPDWGT", "PITCH_MAX", "PITCH_MIN", "LAND_SINK", "LAND_TCONST", "LAND_DAMP"]),
        ("SIM_", [""], [f"PARAM{i}" for i in range(210)]),
    ]
    names: list[str] = []
    for head, idx, fields in families:
        for i in idx:
            for fld in fields:
                names.append(f"{head}{i}{fld}")
    names = [s for s in dict.fromkeys(names) if len(s) <= 16][:n]
    assert len(names) == n
    rng = np.random.default_rng(seed)
    scales = [1.0, 1500.0, 0.035, -12.5, 1e-4, 3.0e5]
    store = ParamStore([ParamSpec(name, scales[k % len(scales)] * (1 + k % 3), doc="synthetic")
                        for k, name in enumerate(names)])
    for name in names:
        if rng.random() < 1 / 3:
            store.set(name, store[name] + float(rng.normal(0, 10.0 ** rng.integers(-3, 4))))
    return store


def uav_store() -> ParamStore:
    return ParamStore(uav_param_specs())


# ---------------------------------------------------------------------------- (a) MAVProxy's decoder
def _decode(data: bytes):
    pdata = param_ftp.ftp_param_decode(data)
    assert pdata is not None, "MAVProxy could not decode the file"
    return pdata


@pytest.mark.parametrize("with_defaults", [False, True])
@pytest.mark.parametrize("table", ["uav", "ardupilot_like_1000"])
def test_mavproxy_decoder_reads_the_store(table, with_defaults):
    store = uav_store() if table == "uav" else ardupilot_like_specs()
    data = param_pck.pack(param_pck.store_entries(store), param_pck.Query(with_defaults=with_defaults))
    pdata = _decode(data)
    assert [n.decode() for n, _, _ in pdata.params] == list(store)
    assert [v for _, v, _ in pdata.params] == [f32(store[n]) for n in store]  # MAVLink's float32
    assert {t for _, _, t in pdata.params} == {param_pck.AP_FLOAT}
    if with_defaults:
        assert [v for _, v, _ in pdata.defaults] == [f32(store.spec(n).default) for n in store]
        assert struct.unpack("<H", data[:2])[0] == param_pck.MAGIC_WITH_DEFAULTS
    else:
        assert pdata.defaults is None


def _value_spans(data: bytes):
    """An independent walk of the format as AP_Filesystem_Param.cpp documents it: per entry,
    the byte span of its last value (the default when it carries one)."""
    magic, num, _total = struct.unpack("<HHH", data[:6])
    i, spans = 6, []
    for _ in range(num):
        while data[i] == 0:  # pad bytes
            i += 1
        width = {1: 1, 2: 2, 3: 4, 4: 4}[data[i] & 0x0F]
        n_values = 2 if (magic == 0x671C and data[i] >> 4 & 1) else 1
        i += 2 + (data[i + 1] >> 4) + 1 + n_values * width
        spans.append((i - width, i))
    assert i == len(data)
    return spans


@pytest.mark.parametrize("block", [239, 100, 37, 7])
def test_no_entry_ends_with_a_value_across_a_read_block(block):
    """ArduPilot's padding rule: an entry's last value never crosses a block boundary, so a
    re-read of one lost block cannot splice half a number."""
    store = ardupilot_like_specs()
    for with_defaults in (False, True):
        data = param_pck.pack(param_pck.store_entries(store), param_pck.Query(with_defaults), block)
        spans = _value_spans(data)
        assert len(spans) == len(store)
        assert [(a, b) for a, b in spans if a // block != (b - 1) // block] == []
        assert len(_decode(data).params) == len(store)  # MAVProxy skips the pad bytes
    assert len(param_pck.pack(param_pck.store_entries(store), block=block)) > len(
        param_pck.pack(param_pck.store_entries(store), block=239)) or block == 239  # pads were needed


@settings(max_examples=150, deadline=None, derandomize=True)
@given(st.lists(st.tuples(st.text("ABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_", min_size=1, max_size=16),
                          st.floats(allow_nan=False, allow_infinity=False, width=32),
                          st.floats(-1e6, 1e6, allow_nan=False, width=32)),
                min_size=1, max_size=60, unique_by=lambda t: t[0]),
       st.booleans())
def test_any_table_round_trips_through_mavproxys_decoder(rows, with_defaults):
    entries = [param_pck.Entry(n, v, d) for n, v, d in rows]
    pdata = _decode(param_pck.pack(entries, param_pck.Query(with_defaults)))
    assert [(n.decode(), v) for n, v, _ in pdata.params] == [(n, f32(v)) for n, v, _ in rows]
    if with_defaults:
        assert [v for _, v, _ in pdata.defaults] == [f32(v if f32(v) == f32(d) else d) for _, v, d in rows]


def test_query_start_count_and_bad_queries():
    store = ardupilot_like_specs()
    entries = param_pck.store_entries(store)
    data = param_pck.pack(entries, param_pck.parse_query("start=10&count=5&foo=bar"))
    magic, num, total = struct.unpack("<HHH", data[:6])
    assert (magic, num, total) == (param_pck.MAGIC, 5, 1000)
    assert len(_value_spans(data)) == 5
    for bad in ("withdefaults=2", "start=x", "count=65535", "start=", "start=-1"):
        with pytest.raises(ValueError):
            param_pck.parse_query(bad)
    with pytest.raises(ValueError):
        param_pck.pack(entries, param_pck.Query(start=1000))
    with pytest.raises(ValueError):
        param_pck.pack([])


# ---------------------------------------------------------------------------- wire packets (pymavlink)
class Wire:
    """A GCS (255/230) and vehicle 1/1 joined by real MAVLink 2 frames, both ways."""

    def __init__(self, server: FtpServer):
        self.server = server
        self.gcs_buf = io.BytesIO()
        self.gcs = mavlink2.MAVLink(self.gcs_buf, srcSystem=255, srcComponent=230)
        self.vehicle_rx = mavlink2.MAVLink(None)
        self.vehicle_tx = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
        self.gcs_rx = mavlink2.MAVLink(None)
        self.now = 0.0
        self.requests = self.round_trips = self.tx_bytes = self.rx_bytes = self.frames_down = 0
        self.opcodes: collections.Counter = collections.Counter()  # requests by opcode

    def deliver(self, drop=lambda i, op: False):
        """Frames the GCS wrote -> the server -> reply frames -> the GCS's parser (minus the
        dropped ones).  Returns the replies (pymavlink messages) that arrived."""
        up = self.gcs_buf.getvalue()
        self.gcs_buf.seek(0)
        self.gcs_buf.truncate()
        self.tx_bytes += len(up)
        out, k = [], 0
        msgs = self.vehicle_rx.parse_buffer(up) or []
        if msgs:
            self.round_trips += 1
        for msg in msgs:
            assert msg.get_type() == "FILE_TRANSFER_PROTOCOL"
            self.requests += 1
            self.opcodes[bytes(msg.payload)[3] if len(msg.payload) > 3 else 0] += 1
            for args in self.server.handle_message(msg, self.now, peer=("127.0.0.1", 14550)):
                frame = self.vehicle_tx.file_transfer_protocol_encode(*args).pack(self.vehicle_tx)
                self.vehicle_tx.seq = (self.vehicle_tx.seq + 1) % 256
                self.rx_bytes += len(frame)
                self.frames_down += 1
                for m in self.gcs_rx.parse_buffer(frame) or []:
                    if not drop(k, FtpOp.unpack(bytes(m.payload))):
                        out.append(m)
                    k += 1
        return out

    def request(self, op: FtpOp, drop=lambda i, op: False) -> list[FtpOp]:
        self.gcs.file_transfer_protocol_send(0, 1, 1, list(op.pack()))
        return [FtpOp.unpack(bytes(m.payload)) for m in self.deliver(drop)]


def _open(wire, path=PATH, seq=0, session=3, drop=lambda i, op: False):
    return wire.request(FtpOp(seq=seq, session=session, opcode=OP_OPEN_FILE_RO, size=len(path), data=path), drop)


def _crc_mavproxy(data: bytes) -> int:
    """MAVProxy's FTPWorker.local_file_crc, on bytes instead of a file."""
    worker = mavproxy_ftp.FTPWorker.local_file_crc
    buf = io.BytesIO(data)
    fake_open = types.SimpleNamespace(open=lambda *a, **k: buf)
    g = worker.__globals__
    saved = g.get("open")
    g["open"] = fake_open.open
    try:
        return worker(None, "-")
    finally:
        if saved is None:
            g.pop("open", None)
        else:
            g["open"] = saved


def test_wire_open_burst_terminate_gives_the_store():
    store = ardupilot_like_specs()
    wire = Wire(FtpServer(store))
    (ack,) = _open(wire, PATH + b"?withdefaults=1")
    assert (ack.opcode, ack.req_opcode, ack.seq, ack.session, ack.size) == (OP_ACK, OP_OPEN_FILE_RO, 1, 3, 4)
    size = struct.unpack("<I", ack.data)[0]
    burst = wire.request(FtpOp(seq=1, session=3, opcode=OP_BURST_READ_FILE, size=DATA_LEN))
    data_ops, eof = burst[:-1], burst[-1]
    assert all(o.opcode == OP_ACK and o.burst_complete == 0 for o in data_ops)
    assert (eof.opcode, eof.data[0], eof.burst_complete, eof.offset) == (OP_NAK, ERR_EOF, 1, size)
    assert [o.seq for o in burst] == list(range(2, 2 + len(burst)))  # seq + 1, + 2, ... as ArduPilot
    assert all(o.size == DATA_LEN for o in data_ops[:-1]) and 0 < data_ops[-1].size <= DATA_LEN
    data = b"".join(o.data for o in data_ops)
    assert len(data) == size and [o.offset for o in data_ops] == list(range(0, size, DATA_LEN))
    # the same bytes by ReadFile, block by block, and by the CRC MAVProxy's crclocal computes
    reads = b""
    for seq, ofs in enumerate(range(0, size + DATA_LEN, DATA_LEN), start=10):
        (r,) = wire.request(FtpOp(seq=seq, session=3, opcode=OP_READ_FILE, size=DATA_LEN, offset=ofs))
        if r.opcode == OP_NAK:
            assert r.data[0] == ERR_EOF and ofs >= size
            break
        reads += r.data
    assert reads == data
    (crc,) = wire.request(FtpOp(seq=50, session=9, opcode=OP_CALC_FILE_CRC32, size=len(PATH) + 15,
                                data=PATH + b"?withdefaults=1"))
    assert struct.unpack("<I", crc.data)[0] == _crc_mavproxy(data)
    (term,) = wire.request(FtpOp(seq=51, session=3, opcode=OP_TERMINATE_SESSION))
    assert (term.opcode, term.req_opcode) == (OP_ACK, OP_TERMINATE_SESSION)
    assert wire.server.sessions_open == 0
    pdata = _decode(data)
    assert {n.decode(): v for n, v, _ in pdata.params} == {n: f32(v) for n, v in store.items()}
    assert wire.server.counters["retransmits"] == 0 and wire.server.last_reason is None


def test_lost_replies_are_recovered_with_the_same_seq_or_offset():
    store = ardupilot_like_specs()
    wire = Wire(FtpServer(store))
    assert _open(wire, drop=lambda i, op: True) == []  # the open's Ack is lost
    (ack,) = _open(wire)  # the retry: the same seq and bytes -> the same Ack, not "already open"
    assert ack.opcode == OP_ACK and wire.server.counters["retransmits"] == 1
    assert wire.server.counters["opened"] == 1
    size = struct.unpack("<I", ack.data)[0]
    burst = wire.request(FtpOp(seq=1, session=3, opcode=OP_BURST_READ_FILE, size=DATA_LEN),
                         drop=lambda i, op: i == 17)  # one reply lost in the middle
    got = {o.offset: o.data for o in burst if o.opcode == OP_ACK}
    missing = sorted(set(range(0, size, DATA_LEN)) - set(got))
    assert missing == [17 * DATA_LEN]
    # the client asks again for the gap (a new seq, the lost offset) ...
    (fill,) = wire.request(FtpOp(seq=2, session=3, opcode=OP_READ_FILE, size=DATA_LEN, offset=missing[0]))
    got[fill.offset] = fill.data
    # ... or repeats the whole burst request with its seq: the same replies again
    again = wire.request(FtpOp(seq=1, session=3, opcode=OP_BURST_READ_FILE, size=DATA_LEN))
    assert again[17].data == fill.data and len(again) == len(burst) + 1
    data = b"".join(got[k] for k in sorted(got))
    whole = b"".join(o.data for o in again if o.opcode == OP_ACK)
    assert data == whole and len(data) == size
    assert [v for _, v, _ in _decode(data).params] == [f32(store[n]) for n in store]


def test_figures_for_1000_parameters(capsys):
    """(c) A 1,000-parameter table: round trips, frames and bytes by FTP, against the list
    protocol's PARAM_VALUE stream and ArduPilot's sizes."""
    store = ardupilot_like_specs()
    wire = Wire(FtpServer(store))
    (ack,) = _open(wire, PATH + b"?withdefaults=1")
    burst = wire.request(FtpOp(seq=1, session=3, opcode=OP_BURST_READ_FILE, size=DATA_LEN))
    wire.request(FtpOp(seq=1 + len(burst) + 1, session=3, opcode=OP_TERMINATE_SESSION))
    size = struct.unpack("<I", ack.data)[0]
    plain = len(param_pck.pack(param_pck.store_entries(store)))
    sorted_size = len(param_pck.pack(sorted(param_pck.store_entries(store), key=lambda e: e.name)))
    # the list protocol: one PARAM_VALUE frame per parameter, after PARAM_REQUEST_LIST
    veh = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    list_bytes = sum(len(veh.param_value_encode(n.encode(), store[n], 9, len(store), i).pack(veh))
                     for i, n in enumerate(store))
    with capsys.disabled():
        print(f"\n[ftp figures] 1000 params: {wire.requests} requests, {wire.round_trips} round trips "
              f"(open, burst, terminate), {wire.frames_down} reply frames, {wire.rx_bytes} B down, "
              f"{wire.tx_bytes} B up; param.pck {size} B with defaults ({size / 1000:.2f} B/param), "
              f"{plain} B without ({plain / 1000:.2f} B/param), {sorted_size} B if sorted by name; "
              f"PARAM_VALUE stream {list_bytes} B in 1000 frames")
    assert wire.round_trips == 3 and wire.frames_down == 1 + math.ceil(size / DATA_LEN) + 1 + 1
    # ArduPilot's own expectations: AP_Filesystem_Param::stat estimates 12 B a parameter, MAVProxy's
    # progress 11 B an entry; names sharing prefixes make ours as small
    assert plain / 1000 <= 12.0
    assert wire.rx_bytes < list_bytes / 2


# ---------------------------------------------------------------------------- protocol edges
def _req(server, op: FtpOp, now=0.0, peer="p"):
    return [FtpOp.unpack(r) for r in server.handle(op.pack(), now, peer)]


def test_every_unsupported_or_malformed_request_gets_a_clear_counted_nak():
    srv = FtpServer(uav_store())
    cases = [
        (FtpOp(seq=1, opcode=OP_OPEN_FILE_RO, size=240), ERR_INVALID_DATA_SIZE, "bad_size"),
        (FtpOp(seq=2, opcode=OP_OPEN_FILE_RO, size=3, data=PATH), ERR_INVALID_DATA_SIZE, "bad_name"),
        (FtpOp(seq=3, opcode=OP_OPEN_FILE_RO, size=10, data=b"/etc/passw"), ERR_FILE_NOT_FOUND, "not_found"),
        (FtpOp(seq=4, opcode=OP_OPEN_FILE_RO, size=len(PATH) + 15, data=PATH + b"?withdefaults=7"),
         ERR_FAIL_ERRNO, "bad_query"),
        (FtpOp(seq=5, opcode=OP_READ_FILE, size=10), ERR_INVALID_SESSION, "invalid_session"),
        (FtpOp(seq=6, opcode=OP_BURST_READ_FILE, session=9), ERR_INVALID_SESSION, "invalid_session"),
        (FtpOp(seq=7, opcode=OP_CREATE_FILE, size=len(PATH), data=PATH), ERR_FILE_PROTECTED, "read_only"),
        (FtpOp(seq=8, opcode=OP_WRITE_FILE, size=4, data=b"abcd"), ERR_FILE_PROTECTED, "read_only"),
        (FtpOp(seq=9, opcode=OP_RENAME, size=3, data=b"a\x00b"), ERR_FILE_PROTECTED, "read_only"),
        (FtpOp(seq=10, opcode=OP_TRUNCATE_FILE, size=len(PATH), data=PATH), ERR_UNKNOWN_COMMAND, "unknown_opcode"),
        (FtpOp(seq=11, opcode=OP_LIST_DIRECTORY_WITH_TIME, size=1, data=b"/"), ERR_UNKNOWN_COMMAND,
         "unknown_opcode"),
        (FtpOp(seq=12, opcode=99), ERR_UNKNOWN_COMMAND, "unknown_opcode"),
        (FtpOp(seq=13, opcode=OP_LIST_DIRECTORY, size=4, data=b"/foo"), ERR_FILE_NOT_FOUND, "not_found"),
    ]
    for op, err, reason in cases:
        before = srv.counters[reason]
        (r,) = _req(srv, op)
        assert (r.opcode, r.data[0], r.seq, r.req_opcode) == (OP_NAK, err, op.seq + 1, op.opcode), (op, r)
        assert r.size == (2 if err == ERR_FAIL_ERRNO else 1)
        assert srv.counters[reason] == before + 1 and srv.last_reason and "\n" not in srv.last_reason
    # replies are dropped, counted; undecodable payloads cannot be answered
    for bad in (FtpOp(opcode=OP_ACK).pack(), FtpOp(opcode=OP_NAK).pack()):
        assert srv.handle(bad, 0.0) == []
    assert srv.counters["stray_reply"] == 2
    for bad in ([1, 2, float("nan")], "hello", b"", bytes(252), [300] * 12, None, 3.5, [True] * 12):
        assert srv.handle(bad, 0.0) == []
    assert srv.counters["malformed"] == 8
    # MAVLink 2 strips trailing zeros: a short payload is zero-extended (all zeros: None -> Ack)
    (r,) = [FtpOp.unpack(p) for p in srv.handle(b"\x05", 0.0)]
    assert (r.opcode, r.req_opcode, r.seq) == (OP_ACK, OP_NONE, 6)
    # seq is a u16 and wraps
    (r,) = _req(srv, FtpOp(seq=0xFFFF, opcode=OP_NONE))
    assert (r.opcode, r.seq) == (OP_ACK, 0)
    # the clock: NaN or backwards is counted and ignored
    assert srv.handle(FtpOp(opcode=OP_NONE).pack(), math.nan) and srv.counters["bad_time"] == 1


def test_empty_store_refuses_the_open_so_the_gcs_falls_back():
    srv = FtpServer(ParamStore([]))
    (r,) = _req(srv, FtpOp(opcode=OP_OPEN_FILE_RO, size=len(PATH), data=PATH))
    assert (r.opcode, r.data[0]) == (OP_NAK, ERR_FAIL_ERRNO) and srv.sessions_open == 0


def test_sessions_limits_timeouts_reset_and_already_open():
    srv = FtpServer(uav_store())
    op = lambda s, seq=0: FtpOp(seq=seq, session=s, opcode=OP_OPEN_FILE_RO, size=len(PATH), data=PATH)  # noqa: E731
    for s in range(5):
        assert _req(srv, op(s), now=0.0)[0].opcode == OP_ACK
    (r,) = _req(srv, op(5), now=1.0)
    assert (r.opcode, r.data[0]) == (OP_NAK, ERR_NO_SESSIONS_AVAILABLE)
    (r,) = _req(srv, op(0, seq=7), now=1.0)  # a new open on an open session
    assert (r.opcode, r.data[0]) == (OP_NAK, ERR_FAIL) and srv.counters["already_open"] == 1
    # another peer's sessions are its own; a reset closes only the peer's
    assert _req(srv, FtpOp(seq=1, opcode=OP_RESET_SESSIONS), now=1.5, peer="q")[0].opcode == OP_ACK
    assert srv.sessions_open == 5
    # after 3 s idle the oldest can be taken over by a new open
    (r,) = _req(srv, op(5, seq=2), now=3.5)
    assert r.opcode == OP_ACK and srv.counters["taken_over"] == 1 and srv.sessions_open == 5
    # after 20 s idle every session is closed
    _req(srv, FtpOp(seq=9, opcode=OP_NONE), now=30.0)
    assert srv.sessions_open == 0 and srv.counters["expired"] == 5
    _req(srv, op(1, seq=3), now=31.0)
    assert _req(srv, FtpOp(seq=4, opcode=OP_RESET_SESSIONS), now=31.0)[0].opcode == OP_ACK
    assert srv.sessions_open == 0
    # terminate of a session that is not open: Ack (ArduPilot: closing nothing succeeds)
    assert _req(srv, FtpOp(seq=5, session=77, opcode=OP_TERMINATE_SESSION), now=31.0)[0].opcode == OP_ACK


def test_snapshot_at_open_and_burst_limit():
    store = uav_store()
    srv = FtpServer(store, burst_packets=1)
    _req(srv, FtpOp(seq=0, session=1, opcode=OP_OPEN_FILE_RO, size=len(PATH), data=PATH))
    store.set("NAV_Q", 2.5)  # after the open: the file being read keeps the old value
    (first,) = _req(srv, FtpOp(seq=1, session=1, opcode=OP_BURST_READ_FILE, size=20))
    assert first.burst_complete == 1 and first.size == 20  # the limit reached: the client asks on
    rest = _req(srv, FtpOp(seq=2, session=1, opcode=OP_BURST_READ_FILE, size=20, offset=20))
    data = first.data
    ofs = 20
    seq = 3
    while rest[0].opcode == OP_ACK:
        data += rest[0].data
        ofs += rest[0].size
        rest = _req(srv, FtpOp(seq=seq, session=1, opcode=OP_BURST_READ_FILE, size=20, offset=ofs))
        seq += 1
    assert rest[0].data[0] == ERR_EOF and rest[0].burst_complete == 1
    assert dict((n.decode(), v) for n, v, _ in _decode(data).params)["NAV_Q"] == f32(0.035)
    _req(srv, FtpOp(seq=seq, session=1, opcode=OP_TERMINATE_SESSION))
    _req(srv, FtpOp(seq=0, session=1, opcode=OP_OPEN_FILE_RO, size=len(PATH), data=PATH))
    (r,) = _req(FtpServer(store), FtpOp(seq=0, session=1, opcode=OP_OPEN_FILE_RO, size=len(PATH), data=PATH))
    assert r.opcode == OP_ACK


def test_list_directory():
    srv = FtpServer(uav_store())
    (r,) = _req(srv, FtpOp(opcode=OP_LIST_DIRECTORY, size=1, data=b"/"))
    assert r.opcode == OP_ACK and r.data == b"D@PARAM\x00"
    (r,) = _req(srv, FtpOp(seq=1, opcode=OP_LIST_DIRECTORY, size=7, data=b"@PARAM/"))
    name, size = r.data.rstrip(b"\x00")[1:].split(b"\t")
    assert r.data[:1] == b"F" and name == b"param.pck" and int(size) > 6
    (r,) = _req(srv, FtpOp(seq=2, opcode=OP_LIST_DIRECTORY, size=6, data=b"@PARAM", offset=1))
    assert (r.opcode, r.data[0]) == (OP_NAK, ERR_EOF)


@settings(max_examples=300, deadline=None, derandomize=True)
@given(st.lists(st.tuples(st.integers(0, 3), st.sampled_from([0, 1, 2, 3, 4, 5, 6, 12, 14, 15, 16, 128, 200]),
                          st.integers(0, 255), st.integers(0, 2**32 - 1), st.binary(max_size=239),
                          st.booleans()), max_size=25))
def test_any_request_sequence_never_raises_and_replies_are_well_formed(reqs):
    srv = FtpServer(uav_store(), burst_packets=50)
    t = 0.0
    for session, opcode, size, offset, data, use_path in reqs:
        if use_path:
            data, size = PATH, len(PATH)
        op = FtpOp(seq=len(data), session=session, opcode=opcode, size=size, offset=offset, data=data)
        t += 0.5
        for _ in range(2):  # every request twice: a duplicate gets the same answer
            replies = srv.handle(op.pack(), t)
            assert all(len(r) == PAYLOAD_LEN for r in replies)
            ops = [FtpOp.unpack(r) for r in replies]
            assert all(o.opcode in (OP_ACK, OP_NAK) and o.req_opcode == opcode for o in ops)
            assert [o.seq for o in ops] == [(op.seq + 1 + i) & 0xFFFF for i in range(len(ops))]
    assert srv.sessions_open <= 5


def test_capabilities_and_addressing():
    base = mavlink2.MAV_PROTOCOL_CAPABILITY_MAVLINK2 | mavlink2.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
    caps = advertised_capabilities(base)
    assert caps & mavlink2.MAV_PROTOCOL_CAPABILITY_FTP and caps & base == base
    assert addressed_to(3, 1, 3, 1) and addressed_to(3, 0, 3, 1)
    assert not addressed_to(0, 0, 3, 1) and not addressed_to(4, 1, 3, 1) and not addressed_to(3, 2, 3, 1)


# ---------------------------------------------------------------------------- (b) MAVProxy's client
class _Clock:
    def __init__(self):
        self.t = 1_000_000.0

    def time(self):
        return self.t

    def monotonic(self):
        return self.t

    strftime = staticmethod(__import__("time").strftime)
    localtime = staticmethod(__import__("time").localtime)


class _Master:
    def __init__(self, mav):
        self.mav = mav
        self.fetch_all = 0

    def param_fetch_all(self):
        self.fetch_all += 1

    def time_since(self, _name):
        return 0.0


class FakeMPState:
    """The parts of MAVProxy's MPState that mavproxy_ftp.FTPModule and mavproxy_param.ParamState
    touch (settings, module registry, master link, console), and nothing else."""

    def __init__(self, wire: Wire):
        self.settings = types.SimpleNamespace(source_system=255, source_component=230, target_system=1,
                                              target_component=1, param_ftp=True)
        self.public_modules, self.command_map, self.completions = {}, {}, {}
        self.completion_functions, self.multi_instance, self.instance_count = {}, {}, {}
        self.console = types.SimpleNamespace(set_status=lambda *a, **k: None)
        self.status = types.SimpleNamespace(logdir=None)
        self.logqueue = None
        self._master = _Master(wire.gcs)

    def master(self):
        return self._master

    def module(self, name):
        return self.public_modules.get(name)


def _mavproxy_session(monkeypatch, store, **server_kw):
    clock = _Clock()
    monkeypatch.setattr(mavproxy_ftp, "time", clock)
    wire = Wire(FtpServer(store, **server_kw))
    mp = FakeMPState(wire)
    ftp = mavproxy_ftp.FTPModule(mp)
    pstate = mavproxy_param.ParamState(mavparm.MAVParmDict(), None, None, "mav.parm", mp, (1, 1))
    return clock, wire, mp, ftp, pstate


def _run(clock, wire, ftp, pstate, drop=lambda i, op: False, steps=200, dt=0.02):
    k = [0]

    def counted_drop(_i, op):
        k[0] += 1
        return drop(k[0] - 1, op)

    for _ in range(steps):
        for m in wire.deliver(counted_drop):
            ftp.mavlink_packet(m)
        ftp.idle_task()
        clock.t += dt
        wire.now += dt
        if not pstate.ftp_started and (pstate.mav_param_set or pstate.ftp_failed):
            if not wire.gcs_buf.getvalue():
                break


def test_mavproxy_downloads_every_parameter_by_ftp(monkeypatch, capsys):
    store = ardupilot_like_specs()
    clock, wire, mp, ftp, pstate = _mavproxy_session(monkeypatch, store)
    pstate.fetch_check(mp.master(), force=True)  # what MAVProxy does on connection: FTP first
    assert pstate.ftp_started
    _run(clock, wire, ftp, pstate)
    assert "Received 1000 parameters (ftp)" in capsys.readouterr().out
    assert not pstate.ftp_failed and mp.master().fetch_all == 0
    assert dict(pstate.mav_param) == {n: f32(v) for n, v in store.items()}
    assert {n: pstate.default_params[n] for n in store} == {n: f32(store.spec(n).default) for n in store}
    assert wire.server.sessions_open == 0  # MAVProxy terminated its session
    assert dict(wire.opcodes) == {OP_OPEN_FILE_RO: 1, OP_BURST_READ_FILE: 1, OP_TERMINATE_SESSION: 1}
    assert wire.server.counters["opened"] == 1 and sum(wire.server.counters[r] for r in (
        "malformed", "bad_size", "bad_name", "not_found", "invalid_session", "unknown_opcode")) == 0


def test_mavproxy_recovers_a_lost_open_ack_and_a_lost_burst_packet(monkeypatch, capsys):
    store = ardupilot_like_specs()
    clock, wire, mp, ftp, pstate = _mavproxy_session(monkeypatch, store)
    pstate.fetch_check(mp.master(), force=True)
    # reply 0 is the open Ack (lost: MAVProxy re-sends with the same seq after its timeout);
    # reply 1 is then the re-sent Ack, replies 2.. the burst; number 12 is lost
    _run(clock, wire, ftp, pstate, drop=lambda i, op: i in (0, 12), steps=400)
    assert "Received 1000 parameters (ftp)" in capsys.readouterr().out
    assert dict(pstate.mav_param) == {n: f32(v) for n, v in store.items()}
    c = wire.server.counters
    assert c["retransmits"] == 1 and c["opened"] == 1 and c["already_open"] == 0
    # the open was sent twice with one seq; the lost block came back by one ReadFile of its offset
    assert wire.opcodes[OP_OPEN_FILE_RO] == 2 and wire.opcodes[OP_READ_FILE] == 1
    assert wire.opcodes[OP_BURST_READ_FILE] == 1 and wire.opcodes[OP_TERMINATE_SESSION] == 1
    assert c["bytes_served"] > 0 and wire.server.sessions_open == 0


def test_mavproxy_falls_back_to_the_list_protocol_when_the_open_fails(monkeypatch):
    clock, wire, mp, ftp, pstate = _mavproxy_session(monkeypatch, ParamStore([]))
    pstate.fetch_check(mp.master(), force=True)
    _run(clock, wire, ftp, pstate, steps=20)
    assert pstate.ftp_failed and not pstate.ftp_started
    pstate.fetch_check(mp.master(), force=True)  # its next periodic check (1 s)
    assert mp.master().fetch_all == 1  # PARAM_REQUEST_LIST
