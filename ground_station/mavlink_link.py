"""The ground station as a MAVLink 2 component toward the ground-control endpoint (UDP, pymavlink).

Identity.  System 250, component MAV_COMP_ID_ONBOARD_COMPUTER (191), HEARTBEAT at 1 Hz of
simulation time with type MAV_TYPE_GCS and autopilot MAV_AUTOPILOT_INVALID, base_mode 0,
system_status MAV_STATE_ACTIVE.  Why these (read in the clients' sources):

* MAVSDK (core, mavsdk_impl.cpp / system_impl.cpp): any HEARTBEAT from a system id other than
  0 (and other than QGC's own 255/190) makes the system and marks it connected; the type and
  autopilot only set the vehicle type / autopilot kind, and a component other than 1 means
  ``has_autopilot()`` is false (no AUTOPILOT_VERSION request).  Both MAV_TYPE_GCS and
  MAV_TYPE_ONBOARD_CONTROLLER therefore give "connected".
* MAVProxy 1.8.75 (mavproxy_link.py master_callback, mavproxy_console.py add_new_vehicle,
  mavproxy_arm.py): every HEARTBEAT whose type is not MAV_TYPE_GCS prints "Detected vehicle
  250:191", puts 250 in the vehicle list (``vehicle 250`` selects it) and in the console's
  vehicle menu; MAV_TYPE_GCS is skipped by all three.  MAV_AUTOPILOT_INVALID keeps it from
  being taken as the target system (heartbeat_is_from_autopilot) with either type, and
  pymavlink's probably_vehicle_heartbeat is false for both.  So MAV_TYPE_GCS is the one
  type with which MAVProxy never lists the ground station as something to fly.
* QGroundControl (MultiVehicleManager::_vehicleHeartbeatInfo) creates no vehicle for a
  component other than 1 nor for MAV_TYPE_GCS / ONBOARD_CONTROLLER: either is fine there.

MAVLink blocks (sitl.mavlink.blocks).  A swarm beyond 249 vehicles runs several MAVLink
networks, one GCS address each; the ground station is system 250 on every one: ``gcs`` lists
the blocks' addresses (block 1 first) and every frame below goes to each, packed by the block's
own MAVLink stream (its own sequence numbers; signed on the block's link id -- block k: k - 1 --
with the block's own persisted signing state).  Counters count messages once, whatever the
number of blocks; ``block_frames`` counts the frames each block was sent.  The tlog records
block 1's frames.

Output (every frame signed when a key is given, see sitl.mavlink.signing):

* ADSB_VEHICLE per estimate (beacon, each sonde): position, geometric altitude, velocity,
  callsign ``BEA<id>`` / ``SON<id>``, emitter UAV / LIGHTER_AIR.
* UTM_GLOBAL_POSITION right after it, the per-object uncertainty: ADSB_VEHICLE has no accuracy
  field in common.xml (ICAO_address, lat, lon, altitude_type, altitude, heading, hor_velocity,
  ver_velocity, callsign, emitter_type, tslc, flags, squawk), UTM_GLOBAL_POSITION is common.xml's
  traffic report of ANOTHER aircraft with an id (``uas_id``, here the ADSB callsign, zero padded)
  and 1-sigma fields ``h_acc`` / ``v_acc`` (mm) and ``vel_acc`` (cm/s); PX4 takes it in as
  traffic, MAVSDK decodes it, QGC's MAVLink Inspector and MAVProxy's ``status`` / ``graph`` /
  tlog tools show its fields.  GLOBAL_POSITION_INT_COV was not taken: it is the SENDER's own
  position (one per system/component), so it cannot carry several objects from system 250.
  No GCS draws either on its map: see :func:`uncertainty_1sigma` for the values.
* STATUSTEXT for the trackers' integrity events and the input links' stale/back changes
  (:meth:`GcsLink.integrity_event`, :meth:`GcsLink.link_change`), severity by kind
  (INTEGRITY_SEVERITY), rate-limited in simulation time (two token buckets: WARNING and worse /
  the rest; what is held back is counted and said in one summary line when tokens return).
  Texts longer than 50 bytes go out in 50-byte chunks sharing a STATUSTEXT ``id`` with
  ``chunk_seq`` 0, 1, ... (MAVProxy reassembles them: a chunk shorter than 50 ends the text,
  so a text of exactly k x 50 bytes gets an empty last chunk).

Nothing raises on what an estimate or event holds: a message that cannot be built is not sent
and counted under a reason (``skipped`` for ADSB_VEHICLE, ``uncertainty_skipped`` for
UTM_GLOBAL_POSITION, ``text_skipped`` for events), a field MAVLink cannot carry is clamped and
counted (``clamped``, ``uncertainty_clamped``), and ``last_reason`` keeps the last one as one
line.  ``mav_gs.tlog`` (optional) records what is sent.
"""
from __future__ import annotations

import math
from collections import Counter

import numpy as np
from pymavlink.dialects.v20 import common as m

from sitl.constants import GPS_UTC_LEAP_S

GS_SYSID = 250
GS_COMPID = m.MAV_COMP_ID_ONBOARD_COMPUTER
GS_MAV_TYPE = m.MAV_TYPE_GCS
GS_AUTOPILOT = m.MAV_AUTOPILOT_INVALID
HEARTBEAT_PERIOD_S = 1.0  # simulation time
#: ICAO address bases: inside 0x004000..0x9FFFFF, where MAVProxy's adsb module trusts the
#: message's emitter type -- below it draws a drone, from 0xA00000 an aircraft, and 0xB10000..
#: 0xB1FFFF (the beacon's base until now) a migratory bird (its synthetic-obstacle bands)
ADSB_ICAO = {"beacon": 0x50BEA0, "sonde": 0x50D000}
ADSB_EMITTER = {"beacon": m.ADSB_EMITTER_TYPE_UAV, "sonde": m.ADSB_EMITTER_TYPE_LIGHTER_AIR}
#: STATUSTEXT severity of an integrity event kind (sitl.integrity_events.EVENT_KINDS): a channel
#: excluded (a step that stays, a drift) is a WARNING, one row left out of one epoch a NOTICE,
#: a channel taken back INFO; an unknown kind is said as a NOTICE and counted
INTEGRITY_SEVERITY = {"step": m.MAV_SEVERITY_WARNING, "ramp": m.MAV_SEVERITY_WARNING,
                      "outlier": m.MAV_SEVERITY_NOTICE, "readmit": m.MAV_SEVERITY_INFO}
STATUSTEXT_CHUNK = 50
_GPS_EPOCH_UNIX_S = 315_964_800.0
_UINT16_MAX = 0xFFFF
_COV_NEG_TOL = 1e-9  # an eigenvalue below -tol x the largest |eigenvalue| is not a covariance


def unix_us_from_gps(t_gps_s: float) -> int:
    """Unix microseconds (UTC, the scenario's fixed GPS-UTC offset) of a GPS time."""
    return int(round((float(t_gps_s) - GPS_UTC_LEAP_S + _GPS_EPOCH_UNIX_S) * 1e6))


def uncertainty_1sigma(lat_rad: float, lon_rad: float, cov6) -> tuple[float, float, float]:
    """(horizontal_sigma_m, vertical_sigma_m, speed_sigma_m_s) of a 6 x 6 ECEF [pos, vel]
    covariance at geodetic (lat, lon), rotated to local ENU (sitl.geodesy.enu_rotation):

    * horizontal: sqrt of the LARGER eigenvalue of the 2 x 2 east/north block -- the 1-sigma
      ellipse's semi-major axis, so a circle of that radius holds the 1-sigma ellipse in every
      direction.  Not DRMS (sqrt of the trace: x sqrt 2 too large for a round error) nor CEP
      (~0.59 (s1 + s2): too small along the long axis of an elongated ellipse -- the beacon's
      range-only fix is one, its error lies along the formation's baseline);
    * vertical: sqrt of the up variance;
    * speed: sqrt of the largest eigenvalue of the 3 x 3 ENU velocity block (the worst direction).

    ValueError if cov6 is not a finite symmetric positive semi-definite 6 x 6 matrix (within
    rounding) -- the caller counts it."""
    from sitl.geodesy import enu_rotation

    P = np.asarray(cov6, dtype=float)
    if P.shape != (6, 6):
        raise ValueError(f"shape {P.shape}")
    if not np.all(np.isfinite(P)):
        raise ValueError("non-finite")
    scale = float(np.max(np.abs(P)))
    if not np.allclose(P, P.T, rtol=1e-6, atol=1e-9 * max(scale, 1.0)):
        raise ValueError("not symmetric")
    R = enu_rotation(lat_rad, lon_rad)
    Cp = R @ (0.5 * (P[0:3, 0:3] + P[0:3, 0:3].T)) @ R.T
    Cv = R @ (0.5 * (P[3:6, 3:6] + P[3:6, 3:6].T)) @ R.T
    for name, C in (("position", Cp), ("velocity", Cv)):
        w = np.linalg.eigvalsh(C)
        if w[0] < -_COV_NEG_TOL * max(abs(w[-1]), 1e-300):
            raise ValueError(f"{name} block not positive semi-definite")
    a, b, c = Cp[0, 0], Cp[0, 1], Cp[1, 1]
    lam_h = 0.5 * (a + c) + math.hypot(0.5 * (a - c), b)
    lam_v = float(np.linalg.eigvalsh(Cv)[-1])
    return math.sqrt(max(lam_h, 0.0)), math.sqrt(max(Cp[2, 2], 0.0)), math.sqrt(max(lam_v, 0.0))


class _Bucket:
    """A token bucket in simulation seconds: ``burst`` tokens, ``rate_per_s`` back per second."""

    def __init__(self, burst: float, rate_per_s: float):
        self.burst, self.rate = float(burst), float(rate_per_s)
        self.tokens, self.t = float(burst), None

    def refill(self, t: float) -> None:
        if self.t is not None and t > self.t:
            self.tokens = min(self.burst, self.tokens + (t - self.t) * self.rate)
        if self.t is None or t > self.t:
            self.t = t

    def take(self) -> bool:
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            return True
        return False


class _BlockWriter:
    """pymavlink's MAVLink.send writes a block's packed frames here: to that block's GCS."""

    def __init__(self, sock, addr):
        self.sock, self.addr = sock, addr

    def write(self, buf: bytes) -> None:
        self.sock.sendto(buf, self.addr)


def _per_block(name: str, value, n: int) -> list:
    """One value per block: a list of n, or one value for every block."""
    if isinstance(value, (list, tuple)):
        if len(value) != n:
            raise ValueError(f"{name}: expected one per block ({n}), got {len(value)}")
        return list(value)
    return [value] * n


class GcsLink:
    """The ground station's MAVLink output to ``gcs`` ("HOST:PORT", or a list of them: one per
    MAVLink block, block 1 first); see the module docstring.

    signing_key (32 bytes): every frame signed on ``link_id`` with the timestamps of
    sitl.mavlink.signing (clock: unix seconds, default sitl.pacing.wall_now -- the launcher's
    wall clock, as the vehicles sign; signing_state: a path for the persisted signing state,
    OUT/mav_signing_250.json in a live run, or None).  With several blocks, link_id and
    signing_state are one per block (a list) or, link_id, one for all.  The link never reads,
    so no peer moves its timestamps.

    :meth:`tick` (simulation time, the worker's paced clock) sends the HEARTBEAT when due and
    refills the STATUSTEXT buckets (``text_burst`` messages, ``text_rate_per_s`` per simulated
    second each)."""

    def __init__(self, gcs: str, tlog=None, *, signing_key: bytes | None = None, clock=None, link_id: int = 0,
                 signing_state=None, text_burst: int = 5, text_rate_per_s: float = 1.0):
        import socket

        from sitl.mavlink.framing import TlogWriter, fresh_tlog_path
        from sitl.pacing import wall_now

        texts = [gcs] if isinstance(gcs, str) else list(gcs)
        if not texts:
            raise ValueError("gcs: expected at least one HOST:PORT")
        self.addrs = []
        for t in texts:
            host, _, port = str(t).rpartition(":")
            if not host or not port.isdigit() or not 0 < int(port) < 65536:
                raise ValueError(f"gcs: expected HOST:PORT, got {t!r}")
            self.addrs.append((host, int(port)))
        self.addr = self.addrs[0]
        n = len(self.addrs)
        link_ids = _per_block("link_id", link_id, n)
        states = _per_block("signing_state", signing_state, n)
        if signing_key is not None and (not isinstance(signing_key, (bytes, bytearray)) or len(signing_key) != 32):
            raise ValueError("signing_key must be 32 bytes")
        self._clock = wall_now if clock is None else clock
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setblocking(False)
        # one MAVLink stream per block (sequence numbers, signing); block 1's also encodes and
        # writes through self.write
        self._outs = []
        for k, (addr, lid, st) in enumerate(zip(self.addrs, link_ids, states)):
            mav = m.MAVLink(self if k == 0 else _BlockWriter(self.sock, addr), srcSystem=GS_SYSID,
                            srcComponent=GS_COMPID)
            signing = None
            if signing_key is not None:
                from sitl.mavlink.framing import SigningStateFile
                from sitl.mavlink.signing import OutgoingSigning
                state = SigningStateFile(st, GS_SYSID) if st is not None else None
                signing = OutgoingSigning(mav, bytes(signing_key), clock=self._clock, link_id=int(lid),
                                          state_file=state)
            self._outs.append((mav, signing))
        self.mav, self.signing = self._outs[0]
        self.signed = self.signing is not None
        self.block_frames = [0] * n
        # a new file per start, stamped with the wall clock as MAVProxy's (sitl.mavlink.framing)
        self._tlog = TlogWriter(fresh_tlog_path(tlog), stamp_clock=wall_now) if tlog else None
        self.sent = Counter()
        self.errors = 0
        self.skipped = Counter()  # ADSB_VEHICLE not sent: why
        self.clamped = Counter()  # ADSB_VEHICLE fields sent clamped, their valid flag cleared
        self.uncertainty_skipped = Counter()  # UTM_GLOBAL_POSITION not sent: why
        self.uncertainty_clamped = Counter()  # UTM_GLOBAL_POSITION fields saturated
        self.text_skipped = Counter()  # events not said: why ("rate" = held back by the buckets)
        self.last_reason: str | None = None
        self._ids: dict = {}
        self._next_heartbeat_s: float | None = None
        self._t_sim_s: float | None = None
        self._buckets = {True: _Bucket(text_burst, text_rate_per_s), False: _Bucket(text_burst, text_rate_per_s)}
        self._held: dict = {True: Counter(), False: Counter()}  # by bucket: held-back messages by kind
        self._text_id = 0

    # ------------------------------------------------------------------ plumbing
    def write(self, buf: bytes) -> None:
        """pymavlink's MAVLink.send writes block 1's packed frames here: to block 1's GCS."""
        self.sock.sendto(buf, self.addr)

    def _send(self, msg) -> bool:
        """msg to every block (each packs it with its own sequence and signature); True if some
        block took it (a block's send error is counted in ``errors``)."""
        ok = False
        for k, (mav, signing) in enumerate(self._outs):
            try:
                if signing is not None:
                    signing.before_send()
                mav.send(msg)
                if k == 0 and self._tlog is not None:
                    self._tlog.write(0.0, msg.get_msgbuf())  # stamped by the wall clock (stamp_clock)
                self.block_frames[k] += 1
                ok = True
            except OSError:
                self.errors += 1
        if ok:
            self.sent[msg.get_type()] += 1
        return ok

    def _reason(self, counter: Counter, key: str, line: str) -> None:
        counter[key] += 1
        self.last_reason = " ".join(line.split())[:200]

    # ------------------------------------------------------------------ heartbeat
    def tick(self, t_sim_s: float) -> None:
        """The worker's simulation time now: the HEARTBEAT when due (every HEARTBEAT_PERIOD_S,
        the first at once), the text buckets refilled, a summary of held-back texts when they
        may go.  A non-finite time is ignored (counted)."""
        try:
            t = float(t_sim_s)
        except (TypeError, ValueError):
            t = math.nan
        if not math.isfinite(t):
            self._reason(self.text_skipped, "bad_time", f"tick: time {t_sim_s!r} is not finite")
            return
        self._t_sim_s = t
        for important, b in self._buckets.items():
            b.refill(t)
            held = self._held[important]
            if held and b.tokens >= 1.0:
                b.take()
                n = sum(held.values())
                kinds = ",".join(f"{k}:{v}" for k, v in sorted(held.items()))
                held.clear()
                sev = m.MAV_SEVERITY_WARNING if important else m.MAV_SEVERITY_NOTICE
                self.statustext(f"gs: {n} held back ({kinds})", sev)
        if self._next_heartbeat_s is None or t >= self._next_heartbeat_s:
            self.heartbeat()
            nxt = (t if self._next_heartbeat_s is None else self._next_heartbeat_s) + HEARTBEAT_PERIOD_S
            self._next_heartbeat_s = nxt if nxt > t else t + HEARTBEAT_PERIOD_S  # no burst after a stall

    def heartbeat(self, state: int = m.MAV_STATE_ACTIVE) -> None:
        self._send(self.mav.heartbeat_encode(GS_MAV_TYPE, GS_AUTOPILOT, 0, 0, state))

    # ------------------------------------------------------------------ estimates
    def adsb(self, kind: str, target_id: str, est) -> None:
        """One estimate as ADSB_VEHICLE, then its uncertainty as UTM_GLOBAL_POSITION; never
        raises (see the module docstring)."""
        try:
            out = self._adsb_message(kind, target_id, est)
        except Exception as e:  # whatever else an estimate holds: not sent, counted
            self._reason(self.skipped, f"invalid:{type(e).__name__}",
                         f"ADSB_VEHICLE {kind!r}/{target_id!r} not sent: {type(e).__name__}: {e}")
            return
        if out is None:
            return
        msg, geo = out
        self._send(msg)
        try:
            utm = self._utm_message(est, geo)
        except Exception as e:
            self._reason(self.uncertainty_skipped, f"invalid:{type(e).__name__}",
                         f"UTM_GLOBAL_POSITION {kind!r}/{target_id!r} not sent: {type(e).__name__}: {e}")
            return
        if utm is not None:
            self._send(utm)

    def _adsb_message(self, kind: str, target_id: str, est):
        from sitl.geodesy import ecef_to_geodetic
        if kind not in ADSB_ICAO:
            self._reason(self.skipped, "unknown_kind",
                         f"ADSB_VEHICLE not sent: unknown kind {str(kind)[:20]!r} (one of {', '.join(ADSB_ICAO)})")
            return None
        pos = [float(v) for v in est.pos_ecef_m]
        vel = [float(v) for v in est.vel_ecef_m_s]
        if len(pos) != 3 or len(vel) != 3:
            self._reason(self.skipped, "shape", f"ADSB_VEHICLE {kind}/{target_id} not sent: position/velocity "
                                                f"of {len(pos)}/{len(vel)} values, not 3")
            return None
        if not all(math.isfinite(v) for v in pos):
            self._reason(self.skipped, "non_finite_position", f"ADSB_VEHICLE {kind}/{target_id} not sent: "
                                                              "non-finite position")
            return None
        lat, lon, h = (float(v) for v in ecef_to_geodetic(pos))
        if not (math.isfinite(lat) and math.isfinite(lon) and math.isfinite(h)):
            self._reason(self.skipped, "non_finite_position", f"ADSB_VEHICLE {kind}/{target_id} not sent: "
                                                              "position without a geodetic form")
            return None
        flags = (m.ADSB_FLAGS_VALID_COORDS | m.ADSB_FLAGS_VALID_ALTITUDE | m.ADSB_FLAGS_VALID_HEADING
                 | m.ADSB_FLAGS_VALID_VELOCITY | m.ADSB_FLAGS_VALID_CALLSIGN)
        # ECEF velocity -> ENU
        sl, cl, so, co = math.sin(lat), math.cos(lat), math.sin(lon), math.cos(lon)
        vx, vy, vz = vel
        ve = -so * vx + co * vy
        vn = -sl * co * vx - sl * so * vy + cl * vz
        vu = cl * co * vx + cl * so * vy + sl * vz
        vel_ok = math.isfinite(ve) and math.isfinite(vn) and math.isfinite(vu)
        if not vel_ok:
            self.clamped["velocity"] += 1
            flags &= ~(m.ADSB_FLAGS_VALID_VELOCITY | m.ADSB_FLAGS_VALID_HEADING)
            ve = vn = vu = 0.0
        alt_mm = round(h * 1000.0)
        if not -2**31 <= alt_mm < 2**31:  # int32 mm: +-2147 km
            self.clamped["altitude"] += 1
            flags &= ~m.ADSB_FLAGS_VALID_ALTITUDE
            alt_mm = max(-2**31, min(2**31 - 1, alt_mm))
        hor = round(math.hypot(vn, ve) * 100.0)
        ver = round(vu * 100.0)
        if hor > 65535 or not -32768 <= ver <= 32767:  # uint16 / int16 cm/s
            self.clamped["velocity"] += 1
            flags &= ~m.ADSB_FLAGS_VALID_VELOCITY
            hor, ver = min(hor, 65535), max(-32768, min(32767, ver))
        key = (kind, target_id)
        n = self._ids.setdefault(key, len(self._ids))
        icao = (ADSB_ICAO[kind] + n) & 0xFFFFFFFF
        callsign = f"{kind[:3].upper()}{target_id}".encode("ascii", "replace")[:8]
        heading = (math.degrees(math.atan2(ve, vn)) + 360.0) % 360.0
        msg = self.mav.adsb_vehicle_encode(
            icao, int(round(math.degrees(lat) * 1e7)), int(round(math.degrees(lon) * 1e7)),
            m.ADSB_ALTITUDE_TYPE_GEOMETRIC, int(alt_mm), int(round(heading * 100)) % 36000, int(hor), int(ver),
            callsign, ADSB_EMITTER[kind], 1, flags, 0)
        return msg, (lat, lon, int(alt_mm), flags, (vn, ve, vu) if vel_ok else None, callsign)

    def _utm_message(self, est, geo):
        lat, lon, alt_mm, adsb_flags, vel_ned, callsign = geo
        cov = getattr(est, "cov", None)
        if cov is None:
            self._reason(self.uncertainty_skipped, "no_covariance", "UTM_GLOBAL_POSITION not sent: no covariance")
            return None
        try:
            h_sigma_m, v_sigma_m, speed_sigma_m_s = uncertainty_1sigma(lat, lon, cov)
        except ValueError as e:
            self._reason(self.uncertainty_skipped, "invalid_covariance",
                         f"UTM_GLOBAL_POSITION {callsign.decode('ascii', 'replace')} not sent: covariance {e}")
            return None
        fields = {}
        for name, value, scale in (("h_acc", h_sigma_m, 1e3), ("v_acc", v_sigma_m, 1e3), ("vel_acc", speed_sigma_m_s, 1e2)):
            v = round(value * scale)
            if v > _UINT16_MAX:  # uint16: 65.535 m / 655.35 m/s; the value says ">= that"
                self.uncertainty_clamped[name] += 1
                v = _UINT16_MAX
            fields[name] = int(v)
        flags = m.UTM_DATA_AVAIL_FLAGS_UAS_ID_AVAILABLE | m.UTM_DATA_AVAIL_FLAGS_POSITION_AVAILABLE
        if adsb_flags & m.ADSB_FLAGS_VALID_ALTITUDE:
            flags |= m.UTM_DATA_AVAIL_FLAGS_ALTITUDE_AVAILABLE
        t_us = 0
        t = getattr(est, "t_gps_s", None)
        if t is not None and math.isfinite(float(t)):
            t_us = max(0, min((1 << 64) - 1, unix_us_from_gps(float(t))))
            flags |= m.UTM_DATA_AVAIL_FLAGS_TIME_VALID
        vx = vy = vz = 0
        if vel_ned is not None:  # UTM: x north, y east, z down, cm/s int16
            vn, ve, vu = vel_ned
            cms = [round(vn * 100.0), round(ve * 100.0), round(-vu * 100.0)]
            if all(-32768 <= c <= 32767 for c in cms[:2]):
                vx, vy = cms[0], cms[1]
                flags |= m.UTM_DATA_AVAIL_FLAGS_HORIZONTAL_VELO_AVAILABLE
            else:
                self.uncertainty_clamped["horizontal_velocity"] += 1
            if -32768 <= cms[2] <= 32767:
                vz = cms[2]
                flags |= m.UTM_DATA_AVAIL_FLAGS_VERTICAL_VELO_AVAILABLE
            else:
                self.uncertainty_clamped["vertical_velocity"] += 1
        uas_id = list(callsign.ljust(18, b"\0"))
        return self.mav.utm_global_position_encode(
            t_us, uas_id, int(round(math.degrees(lat) * 1e7)), int(round(math.degrees(lon) * 1e7)), alt_mm, 0,
            vx, vy, vz, fields["h_acc"], fields["v_acc"], fields["vel_acc"], 0, 0, 0, 0,
            m.UTM_FLIGHT_STATE_UNKNOWN, flags)

    # ------------------------------------------------------------------ texts
    def statustext(self, text: str, severity: int = m.MAV_SEVERITY_WARNING) -> None:
        """One text, not rate-limited: a single STATUSTEXT (id 0) up to 50 bytes, else 50-byte
        chunks with a shared id and chunk_seq (an empty last chunk if the length is k x 50)."""
        sev = max(0, min(7, int(severity)))
        data = " ".join(str(text).split()).encode("utf-8", "replace")
        if len(data) <= STATUSTEXT_CHUNK:
            self._send(self.mav.statustext_encode(sev, data, 0, 0))
            return
        data = data[:STATUSTEXT_CHUNK * 255]
        self._text_id = self._text_id % 0xFFFF + 1
        chunks = [data[i:i + STATUSTEXT_CHUNK] for i in range(0, len(data), STATUSTEXT_CHUNK)]
        if len(chunks[-1]) == STATUSTEXT_CHUNK and len(chunks) < 255:
            chunks.append(b"")
        for seq, c in enumerate(chunks):
            self._send(self.mav.statustext_encode(sev, c, self._text_id, seq))

    def notify(self, text: str, severity: int, kind: str = "text") -> bool:
        """A rate-limited text (see tick): said at once while its bucket has a token, else held
        back and counted (``text_skipped["rate"]``) for the summary line."""
        important = int(severity) <= m.MAV_SEVERITY_WARNING
        b = self._buckets[important]
        if self._t_sim_s is not None:
            b.refill(self._t_sim_s)
        if not b.take():
            self._held[important][kind] += 1
            self.text_skipped["rate"] += 1
            return False
        self.statustext(text, severity)
        return True

    def integrity_event(self, ev) -> None:
        """A tracker's IntegrityEvent as one STATUSTEXT line, e.g. "integrity step uav3.G12 5.21"
        (the statistic when it has one); never raises."""
        try:
            kind, channel = str(ev.event), str(ev.channel)
            sev = INTEGRITY_SEVERITY.get(kind)
            if sev is None:
                self._reason(self.text_skipped, "unknown_event_kind",
                             f"integrity event kind {kind[:20]!r} unknown (said as a notice)")
                sev = m.MAV_SEVERITY_NOTICE
            stat = float(getattr(ev, "statistic", math.nan))
            text = f"integrity {kind} {channel}" + (f" {stat:.3g}" if math.isfinite(stat) else "")
        except Exception as e:
            self._reason(self.text_skipped, f"invalid:{type(e).__name__}", f"integrity event not said: {e}")
            return
        self.notify(text, sev, kind)

    def link_change(self, ls) -> None:
        """An input link that turned stale (WARNING) or came back (INFO); never raises."""
        try:
            stale = bool(ls.stale)
            text = f"link {ls.link}: {'stale' if stale else 'back'}"
        except Exception as e:
            self._reason(self.text_skipped, f"invalid:{type(e).__name__}", f"link change not said: {e}")
            return
        self.notify(text, m.MAV_SEVERITY_WARNING if stale else m.MAV_SEVERITY_INFO, "link")

    def status(self) -> dict:
        """The worker status line's ``mavlink`` block."""
        d = {"sent": dict(self.sent), "errors": self.errors, "skipped": dict(self.skipped),
             "clamped": dict(self.clamped), "uncertainty_skipped": dict(self.uncertainty_skipped),
             "uncertainty_clamped": dict(self.uncertainty_clamped), "text_skipped": dict(self.text_skipped)}
        if len(self._outs) > 1:
            d["block_frames"] = list(self.block_frames)
        if self.signing is not None:
            d["signing"] = {"saves": sum(sg.saves for _, sg in self._outs),
                            "errors": sum(sg.errors for _, sg in self._outs)}
        if self.last_reason:
            d["last_reason"] = self.last_reason
        return d

    def close(self) -> None:
        for _, signing in self._outs:
            if signing is not None:
                signing.close()
        try:
            self.sock.close()
        except OSError:
            pass
        if self._tlog is not None:
            self._tlog.close()
            self._tlog = None
