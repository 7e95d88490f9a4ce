"""What a vehicle reports (SI units) and its conversion to MAVLink units (the edge).

:class:`VehicleTelemetry` is filled by the vehicle process from its simulation (nav
estimate, receiver status, attitude) every step; the endpoint converts it with the pure
functions below, which are the only place MAVLink units appear:

    lat/lon  degE7 (int32)     alt  mm (int32)        vel  cm/s (int16 / uint16)
    heading  cdeg 0..35999     h_acc/v_acc  mm        eph/epv  DOP x 100 (unitless)

Heights: the project has no geoid, so "MSL" altitudes are the ellipsoidal heights of the
simulation (GPS_RAW_INT.alt_ellipsoid is the same number).

Time: the simulation clock is GPS time ``t_gps_s``; the unix time MAVLink wants is
UTC = GPS - GPS_UTC_LEAP_S (sitl.timescales), counted from 1970.
"""
from __future__ import annotations

import math
from typing import NamedTuple

from sitl.constants import GPS_UTC_LEAP_S
from sitl.mavlink.framing import SIGNING_EPOCH_UNIX_S  # noqa: F401  (the signing clock's epoch)
from sitl.timescales import GPS_EPOCH

#: unix seconds of the GPS epoch 1980-01-06T00:00:00 UTC (315964800)
GPS_EPOCH_UNIX_S = GPS_EPOCH.timestamp()

INT16_MAX, INT32_MAX, UINT16_MAX, UINT32_MAX, UINT8_MAX = 32767, 2147483647, 65535, 4294967295, 255


class VehicleTelemetry(NamedTuple):
    """One vehicle's reportable state at a step, SI units.

    lat_rad, lon_rad, alt_msl_m: the onboard navigation estimate (GLOBAL_POSITION_INT).
    vel_ned_m_s: (3,) north, east, down velocity, m/s.
    roll_rad, pitch_rad, yaw_rad (yaw = heading, clockwise from north), body rates rad/s.
    fix_type: GPS_FIX_TYPE (0 no GPS, 1 no fix, 2 2D, 3 3D, ...), satellites_visible.
    hdop, vdop: dilutions of precision (None: unknown); eph_m, epv_m: 1-sigma horizontal /
    vertical position accuracy of the receiver, m (None: unknown).
    gps_*: the receiver's own fix when it differs from the nav estimate (None: same).
    alt_rel_m: height above home (None: alt_msl_m - the home height the endpoint recorded).
    battery_voltage_v (None: unknown), battery_remaining_pct (None: unknown).
    armed: flying under its own control (HEARTBEAT SAFETY_ARMED, system_status ACTIVE).
    airspeed_m_s: the airspeed (None: the ground speed stands in: VFR_HUD, the battery's draw).
    nav: the autopilot's guidance (:class:`NavOutput`, NAV_CONTROLLER_OUTPUT; None: not sent).
    ekf: the onboard filter's status (:class:`EkfStatus`, EKF_STATUS_REPORT; None: not sent).
    """

    lat_rad: float
    lon_rad: float
    alt_msl_m: float
    vel_ned_m_s: tuple = (0.0, 0.0, 0.0)
    roll_rad: float = 0.0
    pitch_rad: float = 0.0
    yaw_rad: float = 0.0
    fix_type: int = 3
    satellites_visible: int | None = None
    hdop: float | None = None
    vdop: float | None = None
    eph_m: float | None = None
    epv_m: float | None = None
    gps_lat_rad: float | None = None
    gps_lon_rad: float | None = None
    gps_alt_msl_m: float | None = None
    gps_vel_ned_m_s: tuple | None = None
    alt_rel_m: float | None = None
    rollspeed_rad_s: float = 0.0
    pitchspeed_rad_s: float = 0.0
    yawspeed_rad_s: float = 0.0
    battery_voltage_v: float | None = None
    battery_remaining_pct: float | None = None
    armed: bool = True
    airspeed_m_s: float | None = None
    nav: "NavOutput | None" = None
    ekf: "EkfStatus | None" = None


class NavOutput(NamedTuple):
    """The autopilot's guidance at a step, SI (NAV_CONTROLLER_OUTPUT converts).

    nav_roll_rad / nav_pitch_rad: the bank and flight-path angle the guidance demands;
    nav_bearing_rad: the heading it steers to; target_bearing_rad: the bearing from the UAV to
    its target point; wp_dist_m: the horizontal distance to it; alt_error_m: target altitude -
    altitude (positive: below it); aspd_error_m_s: commanded - actual airspeed; xtrack_error_m:
    the distance off the leg (previous point -> target), positive left of it (ArduPilot's L1
    sign: the cross product of the UAV's offset from the leg's start with the leg's direction)."""

    nav_roll_rad: float
    nav_pitch_rad: float
    nav_bearing_rad: float
    target_bearing_rad: float
    wp_dist_m: float
    alt_error_m: float
    aspd_error_m_s: float
    xtrack_error_m: float


class EkfStatus(NamedTuple):
    """The onboard filter's status at a step (EKF_STATUS_REPORT converts).

    flags: EKF_STATUS_FLAGS bits.  vel_test_ratio, pos_test_ratio, hgt_test_ratio: ArduPilot's
    innovation test ratios (innovation^2 / (gate^2 x its variance); < 1 passes the gate), which
    EKF_STATUS_REPORT carries as their square roots (NavEKF3_core::getVariances)."""

    flags: int
    vel_test_ratio: float
    pos_test_ratio: float
    hgt_test_ratio: float


def unix_s_from_gps(t_gps_s: float) -> float:
    """Unix seconds (UTC) for GPS seconds: t - GPS_UTC_LEAP_S + 315964800."""
    return float(t_gps_s) - GPS_UTC_LEAP_S + GPS_EPOCH_UNIX_S


def gps_from_unix_s(unix_s: float) -> float:
    return float(unix_s) + GPS_UTC_LEAP_S - GPS_EPOCH_UNIX_S


def _clip_int(x: float, lo: int, hi: int, invalid: int) -> int:
    if x is None or not math.isfinite(x):
        return invalid
    return int(min(max(round(x), lo), hi))


def deg_e7(angle_rad: float) -> int:
    """Angle in rad -> degE7 (int32), rounded to nearest (~1.1 cm of latitude)."""
    return _clip_int(math.degrees(angle_rad) * 1e7, -INT32_MAX - 1, INT32_MAX, 0)


def mm(x_m: float) -> int:
    """Metres -> int32 mm."""
    return _clip_int(x_m * 1000.0, -INT32_MAX - 1, INT32_MAX, 0)


def cm_s16(v_m_s: float) -> int:
    """m/s -> int16 cm/s (saturating)."""
    return _clip_int(v_m_s * 100.0, -INT16_MAX - 1, INT16_MAX, 0)


def cdeg_heading(angle_rad: float, invalid: int = UINT16_MAX) -> int:
    """Heading in rad -> cdeg in 0..35999 (invalid if not finite)."""
    if angle_rad is None or not math.isfinite(angle_rad):
        return invalid
    return int(round(math.degrees(angle_rad) * 100.0)) % 36000


def dop_x100(dop: float | None) -> int:
    return UINT16_MAX if dop is None or not math.isfinite(dop) or dop < 0 else min(int(round(dop * 100.0)), UINT16_MAX - 1)


def acc_mm(sigma_m: float | None) -> int:
    """Accuracy in m -> uint32 mm (0 when unknown, as the extension fields default)."""
    if sigma_m is None or not math.isfinite(sigma_m) or sigma_m < 0:
        return 0
    return min(int(round(sigma_m * 1000.0)), UINT32_MAX)


def ground_speed_course(vel_ned_m_s) -> tuple[float, float]:
    """(horizontal speed m/s, course over ground rad in [0, 2 pi))."""
    vn, ve = float(vel_ned_m_s[0]), float(vel_ned_m_s[1])
    return math.hypot(vn, ve), math.atan2(ve, vn) % (2.0 * math.pi)


def gps_raw_int_fields(tel: VehicleTelemetry, time_usec: int) -> tuple:
    """Arguments of gps_raw_int_encode, in its order (MAVLink units)."""
    lat = tel.gps_lat_rad if tel.gps_lat_rad is not None else tel.lat_rad
    lon = tel.gps_lon_rad if tel.gps_lon_rad is not None else tel.lon_rad
    alt = tel.gps_alt_msl_m if tel.gps_alt_msl_m is not None else tel.alt_msl_m
    vel = tel.gps_vel_ned_m_s if tel.gps_vel_ned_m_s is not None else tel.vel_ned_m_s
    speed, cog = ground_speed_course(vel)
    fix = int(tel.fix_type)
    sats = UINT8_MAX if tel.satellites_visible is None else max(0, min(int(tel.satellites_visible), UINT8_MAX - 1))
    return (int(time_usec), fix, deg_e7(lat), deg_e7(lon), mm(alt), dop_x100(tel.hdop), dop_x100(tel.vdop),
            _clip_int(speed * 100.0, 0, UINT16_MAX - 1, UINT16_MAX),
            cdeg_heading(cog) if speed > 0.05 else UINT16_MAX, sats,
            mm(alt), acc_mm(tel.eph_m), acc_mm(tel.epv_m), 0, 0, 0)


def global_position_int_fields(tel: VehicleTelemetry, time_boot_ms: int, home_alt_msl_m: float) -> tuple:
    """Arguments of global_position_int_encode, in its order (MAVLink units)."""
    rel = tel.alt_rel_m if tel.alt_rel_m is not None else tel.alt_msl_m - home_alt_msl_m
    v = tel.vel_ned_m_s
    return (int(time_boot_ms) & UINT32_MAX, deg_e7(tel.lat_rad), deg_e7(tel.lon_rad), mm(tel.alt_msl_m), mm(rel),
            cm_s16(v[0]), cm_s16(v[1]), cm_s16(v[2]), cdeg_heading(tel.yaw_rad))


def attitude_fields(tel: VehicleTelemetry, time_boot_ms: int) -> tuple:
    yaw = math.remainder(float(tel.yaw_rad), 2.0 * math.pi)  # ATTITUDE.yaw is in -pi..pi
    return (int(time_boot_ms) & UINT32_MAX, float(tel.roll_rad), float(tel.pitch_rad), yaw,
            float(tel.rollspeed_rad_s), float(tel.pitchspeed_rad_s), float(tel.yawspeed_rad_s))


def battery_fields(tel: VehicleTelemetry) -> tuple[int, int]:
    """(voltage_battery mV (UINT16_MAX unknown), battery_remaining % (-1 unknown))."""
    mv = UINT16_MAX if tel.battery_voltage_v is None else _clip_int(tel.battery_voltage_v * 1000.0, 0,
                                                                     UINT16_MAX - 1, UINT16_MAX)
    pct = -1 if tel.battery_remaining_pct is None else _clip_int(tel.battery_remaining_pct, 0, 100, -1)
    return mv, pct


def _deg_i16(angle_rad: float) -> int:
    """Angle rad -> int16 degrees in -180..180 (0 if not finite)."""
    if angle_rad is None or not math.isfinite(angle_rad):
        return 0
    return int(round(math.degrees(math.remainder(float(angle_rad), 2.0 * math.pi))))


def _finite(x: float) -> float:
    return float(x) if x is not None and math.isfinite(x) else 0.0


def nav_controller_output_fields(nav: NavOutput) -> tuple:
    """Arguments of nav_controller_output_encode, in its order: nav_roll, nav_pitch deg (float),
    nav_bearing, target_bearing int16 deg (-180..180), wp_dist uint16 m (saturating),
    alt_error m, aspd_error m/s (the MAVLink unit; ArduPlane sends cm/s, a historic bug),
    xtrack_error m."""
    return (math.degrees(_finite(nav.nav_roll_rad)), math.degrees(_finite(nav.nav_pitch_rad)),
            _deg_i16(nav.nav_bearing_rad), _deg_i16(nav.target_bearing_rad),
            _clip_int(nav.wp_dist_m, 0, UINT16_MAX, 0), _finite(nav.alt_error_m), _finite(nav.aspd_error_m_s),
            _finite(nav.xtrack_error_m))


def _sqrt_ratio(r: float) -> float:
    return math.sqrt(r) if r is not None and math.isfinite(r) and r >= 0 else 0.0


def ekf_status_report_fields(ekf: EkfStatus) -> tuple:
    """Arguments of ekf_status_report_encode, in its order (flags, velocity_variance,
    pos_horiz_variance, pos_vert_variance, compass_variance, terrain_alt_variance,
    airspeed_variance): the "variances" are sqrt(test ratio), as NavEKF3_core::send_status_report
    fills them; no compass, terrain or airspeed fusion here: 0."""
    return (int(ekf.flags) & 0xFFFF, _sqrt_ratio(ekf.vel_test_ratio), _sqrt_ratio(ekf.pos_test_ratio),
            _sqrt_ratio(ekf.hgt_test_ratio), 0.0, 0.0, 0.0)
