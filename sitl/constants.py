"""Physical and system constants, SI units.

Sources: IS-GPS-200 (GPS), GLONASS ICD ed. 5.1 (2008) and PZ-90.11 (GLONASS),
NIMA TR8350.2 (WGS-84).
"""
from __future__ import annotations

from dataclasses import dataclass

C_M_S = 299_792_458.0  # speed of light, m/s

# GPS L1 carrier and GLONASS L1 FDMA plan: f = 1602 MHz + k * 0.5625 MHz, k = -7..+6.
F_GPS_L1_HZ = 1575.42e6
F_GLO_L1_BASE_HZ = 1602.0e6
F_GLO_L1_STEP_HZ = 0.5625e6

# Seconds between the GPS epoch (1980-01-06 00:00 UTC) and the Unix epoch, and the
# GPS-UTC leap seconds in force since 2017-01-01 (no leap second announced since).
GPS_UNIX_OFFSET_S = 315_964_800.0
GPS_UTC_LEAP_S = 18.0
GLONASS_UTC_OFFSET_S = 3 * 3600.0  # GLONASS time = UTC(SU) + 3 h


@dataclass(frozen=True)
class Ellipsoid:
    """A reference ellipsoid with its Earth parameters (GM, rotation rate)."""

    name: str
    a_m: float  # semi-major axis
    f: float  # flattening
    gm_m3_s2: float  # geocentric gravitational constant
    omega_rad_s: float  # Earth rotation rate

    @property
    def b_m(self) -> float:
        return self.a_m * (1.0 - self.f)

    @property
    def e2(self) -> float:
        return self.f * (2.0 - self.f)


WGS84 = Ellipsoid("WGS-84", 6_378_137.0, 1.0 / 298.257223563, 3.986004418e14, 7.2921151467e-5)
PZ90_11 = Ellipsoid("PZ-90.11", 6_378_136.0, 1.0 / 298.25784, 3.986004418e14, 7.292115e-5)

# GPS ICD value of GM used in broadcast-ephemeris propagation (differs from WGS-84's
# 3.986004418e14 in the last digits, and the ICD requires it).
GM_GPS_M3_S2 = 3.986005e14
OMEGA_E_GPS_RAD_S = 7.2921151467e-5

ELLIPSOIDS = {"wgs84": WGS84, "pz90.11": PZ90_11, "pz90": PZ90_11}


def ellipsoid(name_or_obj: "str | Ellipsoid | None") -> Ellipsoid:
    """Resolve an ellipsoid by name ('wgs84', 'pz90.11'); None means WGS-84."""
    if name_or_obj is None:
        return WGS84
    if isinstance(name_or_obj, Ellipsoid):
        return name_or_obj
    key = str(name_or_obj).lower().replace("-", "").replace("_", "")
    key = {"wgs84": "wgs84", "pz90.11": "pz90.11", "pz9011": "pz90.11", "pz90": "pz90"}.get(key, key)
    try:
        return ELLIPSOIDS[key]
    except KeyError:
        raise ValueError(f"unknown ellipsoid {name_or_obj!r}; expected one of {sorted(ELLIPSOIDS)}") from None


def glonass_l1_hz(k):
    """GLONASS L1 carrier for FDMA channel k (-7..+6), Hz. Works on arrays."""
    return F_GLO_L1_BASE_HZ + k * F_GLO_L1_STEP_HZ

#: MAVLink system ids of vehicles in one MAVLink network (a "block", sitl.mavlink.blocks): 1..249
#: (250 is the ground station's: HEARTBEAT / ADSB / STATUSTEXT; 255 the GCS's)
MAX_MAVLINK_VEHICLES = 249
#: MAVLink networks (blocks) a run may have: block k's vehicles listen on base_port + (k - 1) + 10 j
MAX_MAVLINK_BLOCKS = 10
#: vehicles a run may have with MAVLink on: MAX_MAVLINK_BLOCKS full blocks
MAX_MAVLINK_FLEET = MAX_MAVLINK_BLOCKS * MAX_MAVLINK_VEHICLES
