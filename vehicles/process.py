"""The vehicle-group worker of a live run: ``python -m vehicles.process SPEC.json``.

One process steps a group of UAVs as arrays (vehicles.uav swarm, GNSS receivers and onboard
EKFs of vehicles.uav_nav), the beacon (vehicles.beacon) and the beacon links
(sitl.radio.beacon_link) at each of its UAVs; the first group also flies the radiosonde
(vehicles.sonde) with its relay and radar (sitl.radio). Every epoch (1 / run.rate_hz of
simulated time) it publishes on the bus what the batch experiments publish on the in-memory
bus (sitl/app/experiments/beacon/ and sonde/ build the same objects):

    <run>/uav/<i>/nav               UavNav               each UAV's onboard estimate
    <run>/uav/<i>/beacon/<b>        BeaconMeasurement    range / Doppler + the UAV's nav snapshot
    <run>/sonde/<s>/relay           SondeRelay           relayed GNSS at the ground receiver
    <run>/radar/<r>/sonde/<s>       RadarMeasurement     when the radar has a valid range
    <run>/truth/{uav,beacon,sonde}/<id>  Truth           for scoring only

and drives each vehicle's MAVLink endpoint (vehicles.mavlink) with its telemetry. The UAVs'
messages (nav, beacon, truth) go out columnar by default: one ``<run>/uavs/<group>/epoch``
UavGroupEpoch per chunk of up to 100 UAVs per epoch, holding exactly those messages (its
``per_uav`` gives them back, keys and order included; the ground station and the bus log take
them apart, so what they see is the table above). Building and encoding one message per UAV
was a quarter of a world step (bench live, 200 UAVs). With bus fault filters on the transport
the group publishes per UAV (a fault rule names a UAV's keys).

`VehicleGroup` is the step function (simulation time in, messages out, no clock, no sleep);
the worker main paces it with sitl.pacing. A batch run steps the same object over an
InMemoryTransport (tests, ``skyfuse run --batch``).

The beacon's motion is deterministic, so every group flies its own copy (a group's links
need the beacon); only the first group publishes its truth. Each group draws from its own
SeedSequence child of run.seed.

A restarted group (the launcher restarts a worker that died) is a new incarnation: its
messages carry ``incarnation`` = the worker's restart count, so the ground station takes them
as new streams. It resumes the checkpoint its previous incarnation wrote (``OUT/state/<worker>.pkl``,
at most `CHECKPOINT_WALL_S` old: the whole group, its random generators included): it is the
simulator that died, not the vehicles, so the group steps through the gap without publishing
(`VehicleGroup.catch_up`) and goes on as if it had never stopped -- the flight, the sensors'
error processes and the onboard filters continue; what it would have published in the gap
is lost, as over a dead link. Without a checkpoint (none written yet, or unreadable) it
starts afresh from the seed: the deterministic world where it is at the restart epoch (the
sonde's flight re-simulated from launch), the error processes from their initial state, the
onboard filters from a least-squares fix (a receiver's cold start).
"""
from __future__ import annotations

import math
import sys
from dataclasses import dataclass

import numpy as np

from sitl.bus import (
    BeaconMeasurement,
    RadarMeasurement,
    SondeRelay,
    Truth,
    UavGroupEpoch,
    UavNav,
    key_for,
)
from sitl.bus.schema import PART_BEACON, PART_NAV, PART_TRUTH, UAV_GROUP_MAX
from sitl.radio import beacon_link

SONDE_WORLD_KEYS = ("flight", "radar", "relay")


def _phases(global_idx, period_s: float, rate_hz: float) -> np.ndarray:
    """Each UAV's offset (s) within a period of period_s, spread over the period's epochs by
    its global index (so that groups in several processes interleave too)."""
    slots = max(1, int(round(period_s * rate_hz)))
    return (np.asarray(global_idx, dtype=int) % slots) * (period_s / slots)


def _due(next_t: np.ndarray, t: float, period_s: float) -> np.ndarray:
    """Which entries of next_t are due at t; advances those by whole periods past t, keeping
    their phase (an epoch skipped under load does not bunch them up again)."""
    due = t >= next_t - 1e-9
    if due.any():
        next_t[due] += (np.floor((t - next_t[due]) / period_s + 1e-9) + 1.0) * period_s
    return due


@dataclass
class Telemetry:
    """One vehicle's state for its MAVLink endpoint (SI; the endpoint converts)."""

    kind: str  # "uav" | "sonde"
    index: int  # global vehicle index (vehicle number - 1; = sysid - 1 in MAVLink block 1)
    t_gps_s: float
    lat_rad: float
    lon_rad: float
    alt_msl_m: float
    vel_ned_m_s: tuple
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    fix_type: int
    satellites_visible: int
    eph_m: float  # 1-sigma-type horizontal / vertical accuracy, m (GPS_RAW_INT h_acc / v_acc)
    epv_m: float
    hdop: float | None = None
    vdop: float | None = None
    armed: bool = True
    airspeed_m_s: float | None = None
    nav: object = None  # vehicles.mavlink.telemetry.NavOutput (NAV_CONTROLLER_OUTPUT)
    ekf: object = None  # vehicles.mavlink.telemetry.EkfStatus (EKF_STATUS_REPORT)


def _ecef_to_ned(vel_ecef, lat, lon):
    sl, cl, so, co = math.sin(lat), math.cos(lat), math.sin(lon), math.cos(lon)
    vx, vy, vz = vel_ecef
    e = -so * vx + co * vy
    n = -sl * co * vx - sl * so * vy + cl * vz
    u = cl * co * vx + cl * so * vy + sl * vz
    return (n, e, -u)


class VehicleGroup:
    """A group of UAVs (+ the beacon, + optionally the sonde), stepped epoch by epoch.

    scn: sitl.scenario.Scenario; uav_indices: the global indices of this group's UAVs;
    transport: a sitl.bus Transport; rng_seq: this group's numpy SeedSequence; incarnation: which
    life of the worker this is (0 first, the launcher counts restarts), in every message it
    publishes, so that the ground station takes a restarted group's messages (whose sequence
    numbers start over) as a new stream, not as repeats."""

    def __init__(self, scn, uav_indices, transport, rng_seq: np.random.SeedSequence, *,
                 with_beacon_truth: bool = True, with_sonde: bool = True, with_truth: bool = True,
                 incarnation: int = 0, columnar: bool | None = None):
        from sitl.gnss import orbits
        from vehicles import beacon as beacon_mod
        from vehicles import uav as uav_mod
        from vehicles import uav_nav

        self.scn = scn
        self.run_id = scn.run.id
        self.bus = transport
        self.t0 = scn.run.t0_gps_s
        self.idx = list(uav_indices)
        self.n = len(self.idx)
        self.with_beacon_truth = with_beacon_truth
        self.with_truth = with_truth
        self.inc = int(incarnation)
        self.columnar = columnar
        streams = rng_seq.spawn(2)
        self.rng = np.random.default_rng(streams[0])
        self.epoch = 0
        self.sent = 0
        self.t_last: float | None = None
        self.links_nonpositive = 0
        self.b_id = scn.beacon.id
        run = self.run_id
        # UAVs, [uavs].pattern: "orbit", level clockwise circles about [uavs].center through each
        # start, held by guidance (vehicles.uav.Racetrack); "north", the seed 002 sinusoidal law
        # (speed +- 10 m/s, climb 15 cos(0.01 t)) heading north
        self.swarm = None
        self.fleet = None
        if self.n:
            pts = np.array(scn.uavs.start_points())[self.idx]
            if scn.uavs.pattern == "orbit":
                lat_c, lon_c = (math.radians(v) for v in scn.uavs.center)
                law = uav_mod.Racetrack.orbit_through(np.radians(pts[:, 0]), np.radians(pts[:, 1]), lat_c, lon_c,
                                                      scn.uavs.speed_m_s)
            else:
                law = uav_mod.SinusoidalLaw(speed_mean_m_s=np.full(self.n, scn.uavs.speed_m_s), speed_amp_m_s=10.0,
                                            speed_omega_rad_s=0.02, heading0_rad=0.0, climb_amp_m_s=15.0,
                                            climb_omega_rad_s=0.01)
            ground = scn.uavs.start == "ground"
            if ground:  # [uavs] start = "ground": on the ground below their starts, disarmed
                pts = pts.copy()
                pts[:, 2] = scn.uavs.ground_alt_m
            self.swarm = uav_mod.UavSwarm(law, np.radians(pts[:, 0]), np.radians(pts[:, 1]), pts[:, 2])
            self.fleet = self._autopilots(scn, in_flight=not ground)
            self.batteries = self._batteries()
            self.const = orbits.gps_constellation()
            self.nav_cfg = uav_nav.NavConfig()
            self.nav = uav_nav.OnboardNav(self.const, self.nav_cfg)
            self._uav_nav = uav_nav
            self.link_cfg = beacon_link.BeaconLinkConfig()
        b = scn.beacon
        self.beacon = beacon_mod.example_beacon(b.mode, start=b.start)
        self.k_nav = [key_for(run, UavNav, uav=i + 1) for i in self.idx]
        self.k_bm = [key_for(run, BeaconMeasurement, uav=i + 1, beacon=self.b_id) for i in self.idx]
        self.k_tu = [key_for(run, Truth, kind="uav", id=i + 1) for i in self.idx]
        self.k_tb = key_for(run, Truth, kind="beacon", id=self.b_id)
        self.src = [f"uav{i + 1}" for i in self.idx]
        self._columnar_keys()
        self.last_uav_truth = None
        self.last_nav = None
        self.nav_prior = None  # the estimate the last update started from (EKF_STATUS_REPORT's test ratios)
        self.last_tracked = None  # (n, S) the satellites each receiver tracked at the last epoch (DOP)
        self.ap_events: list = []  # the autopilots' events of the last epoch (the endpoints take theirs)
        self.ap_epoch = -1  # the epoch those events belong to
        # the 1 Hz-ish traffic (UavNav at nav_rate_hz, the UAVs' truth at 1 Hz) is spread over the
        # epochs of its period by UAV index: all of it in one epoch made every tenth epoch ~3x the
        # others' work (bench live: vehicle step p99 150-180 ms against p50 35-45 ms at 200 UAVs)
        self._nav_next = None  # (n,) next due time per UAV, set at the first epoch
        self._truth_next = None
        self.sonde = None
        if with_sonde:
            self._build_sonde(streams[1])

    # ------------------------------------------------------------------ sonde
    def _build_sonde(self, seq: np.random.SeedSequence) -> None:
        from sitl.geodesy import ecef_to_geodetic, enu_to_ecef
        from sitl.gnss.orbits import default_constellation
        from sitl.radio.radar import Radar, RadarParams
        from sitl.radio.relay import Relay, RelayParams
        from vehicles.sonde import SondeFlight, SondeParams

        s = self.scn.sonde
        dt = 1.0 / self.scn.run.rate_hz
        rngs = [np.random.default_rng(c) for c in seq.spawn(3)]
        lat0, lon0, h0 = math.radians(s.launch[0]), math.radians(s.launch[1]), s.launch[2]
        b = math.radians(s.gcpp_bearing_deg)
        enu = np.array([s.gcpp_offset_m * math.sin(b), s.gcpp_offset_m * math.cos(b), 0.0])
        lat, lon, h = (float(v) for v in ecef_to_geodetic(enu_to_ecef(enu, lat0, lon0, h0)))
        t0 = self.t0
        self.flight = SondeFlight([rngs[0]], launch_lat_rad=lat0, launch_lon_rad=lon0, launch_h_m=h0, t0_gps_s=t0,
                                  params=SondeParams.with_wind_scale(s.wind_scale), dt_s=dt)
        self.radar = Radar([rngs[1]], site_lat_rad=lat, site_lon_rad=lon, site_h_m=h,
                           params=RadarParams(loss_schedule=((t0 + s.radar_loss_s[0], t0 + s.radar_loss_s[1]),)),
                           batch_shape=(1,))
        self.relay = Relay([rngs[2]], default_constellation("GR"), ground_lat_rad=lat, ground_lon_rad=lon,
                           ground_h_m=h, params=RelayParams(outage_schedule=((t0 + s.gnss_outage_s[0],
                                                                             t0 + s.gnss_outage_s[1]),)),
                           batch_shape=(1,))
        run = self.run_id
        self.sonde = s
        self.k_relay = key_for(run, SondeRelay, sonde=s.id)
        self.k_radar = key_for(run, RadarMeasurement, radar=s.radar_id, sonde=s.id)
        self.k_ts = key_for(run, Truth, kind="sonde", id=s.id)
        self.last_sonde = None
        self.last_relay = None

    # ------------------------------------------------------------------ one epoch
    def _publish(self, key, msg) -> None:
        self.bus.publish(key, msg)
        self.sent += 1

    def step(self, t_gps_s: float, between=None) -> None:
        """Advance the world to t_gps_s (> the previous epoch) and publish the epoch.

        between: None, or a callable run between the slices of the step: after the UAVs' flight
        (and their batteries), and between the UAVs' part and the sonde's. The worker serves the
        MAVLink sockets there, so a command waits for one slice of a long step, not the whole of
        it. What a command changes there: a UAV's mode or mission from the next epoch's flight,
        as ever; a navigation parameter already for this epoch's receivers and filters (both read
        it after the first slice, so they agree); the sonde's flight model is fixed."""
        t = float(t_gps_s)
        if self.t_last is not None and not t > self.t_last:
            raise ValueError(f"t_gps_s must increase: {t} after {self.t_last}")
        k = self.epoch
        trel = t - self.t0
        tb = self.beacon.step(trel)
        B, VB = np.asarray(tb.pos_ecef_m).reshape(3), np.asarray(tb.vel_ecef_m_s).reshape(3)
        if self.with_beacon_truth and self.with_truth:
            self._publish(self.k_tb, Truth(t_gps_s=t, source_id="truth", seq=k, incarnation=self.inc, kind="beacon", pos_ecef_m=B,
                                           vel_ecef_m_s=VB))
        if self.n:
            self._step_uavs(t, k, trel, B, VB, between)
        if self.sonde is not None:
            if between is not None and self.n:
                between()
            self._step_sonde(t, k)
        self.epoch += 1
        self.t_last = t

    def _step_uavs(self, t, k, trel, B, VB, between=None) -> None:
        un = self._uav_nav
        tu = self.fleet.step(trel)  # the scenario's flight, bit-for-bit, until a GCS commands
        self.ap_events, self.ap_epoch = self.fleet.events, k
        U, V = tu.pos_ecef_m, tu.vel_ecef_m_s
        self.last_uav_truth = tu
        # the batteries draw at the flown airspeed (no wind: the truth's speed) while armed
        ap = self.fleet.ap
        self.batteries.step(t, tu.speed_m_s, ap.armed, getattr(ap.C, "batt_capacity_mah", None))
        if between is not None:  # the flight and its batteries are done; the sensors read the config from here
            between()
        ep = un.gnss_measure(self.rng, t, U, V, self.const, self.nav_cfg)
        self.nav_prior = self.nav.estimate
        est = self.nav.update(ep)
        self.last_nav = est
        self.last_tracked = ep.tracked
        meas = beacon_link.measure(self.rng, U, V, B, VB, self.link_cfg)
        sym = 0.5 * (est.P + np.swapaxes(est.P, -1, -2))
        ntr = est.n_tracked.tolist()
        # the UAVs' own truth is for scoring their navigation only (the ground station never
        # reads it): once per simulated second, not every epoch (a third of a swarm's traffic)
        rate = self.scn.run.rate_hz
        if self._nav_next is None:
            self._nav_next = t + _phases(self.idx, 1.0 / self.scn.uavs.nav_rate_hz, rate)
            self._truth_next = t + _phases(self.idx, 1.0, rate)
        nav_due = _due(self._nav_next, t, 1.0 / self.scn.uavs.nav_rate_hz)
        uav_truth = _due(self._truth_next, t, 1.0) if self.with_truth else np.zeros(self.n, bool)
        if self.publishes_columnar:
            self._publish_columnar(t, k, est.x, sym, est.n_tracked, nav_due, uav_truth, meas, U, V)
            return
        nav_due, uav_truth = nav_due.tolist(), uav_truth.tolist()
        r_l, rr_l = meas.range_m.tolist(), meas.range_rate_m_s.tolist()
        vr_l, vv_l = meas.var_range_m2.tolist(), meas.var_range_rate_m2_s2.tolist()
        for i in range(self.n):
            x, C = est.x[i], sym[i]
            fix = 3 if ntr[i] >= 4 else (2 if ntr[i] >= 3 else 0)
            if nav_due[i]:
                self._publish(self.k_nav[i], UavNav(t_gps_s=t, source_id=self.src[i], seq=k, incarnation=self.inc, pos_ecef_m=x[0:3],
                                                    vel_ecef_m_s=x[3:6], cov=C, n_sats=ntr[i], fix_type=fix))
            if not r_l[i] > 0:
                self.links_nonpositive += 1
            else:
                self._publish(self.k_bm[i], BeaconMeasurement(
                    t_gps_s=t, source_id=self.src[i], seq=k, incarnation=self.inc, range_m=r_l[i],
                    range_rate_m_s=rr_l[i],
                    var_range_m2=vr_l[i], var_range_rate_m2_s2=vv_l[i], uav_pos_ecef_m=x[0:3],
                    uav_vel_ecef_m_s=x[3:6], uav_cov=C))
            if uav_truth[i]:
                self._publish(self.k_tu[i], Truth(t_gps_s=t, source_id="truth", seq=k, incarnation=self.inc, kind="uav",
                                                  pos_ecef_m=U[i], vel_ecef_m_s=V[i]))

    def _columnar_keys(self) -> None:
        """The columnar path's ids: one UavGroupEpoch per chunk of at most UAV_GROUP_MAX UAVs,
        keyed ``<run>/uavs/uavs<first>-<last>/epoch`` by its first and last UAV's ids."""
        self.uav_key_ids = [str(i + 1) for i in self.idx]
        self.k_group = []  # (key, group id) per chunk
        for c0 in range(0, self.n, UAV_GROUP_MAX):
            c1 = min(self.n, c0 + UAV_GROUP_MAX)
            gid = f"uavs{self.idx[c0] + 1}-{self.idx[c1 - 1] + 1}"
            self.k_group.append((key_for(self.run_id, UavGroupEpoch, group=gid), gid))

    @property
    def publishes_columnar(self) -> bool:
        """Whether the UAVs' epoch goes out as UavGroupEpoch messages (one per chunk of
        UAV_GROUP_MAX UAVs) rather than up to three messages per UAV: ``columnar`` if given, else
        unless the transport has fault filters (bus faults are per key: a rule on
        ``uav/2/beacon/**`` must see UAV 2's own messages)."""
        if self.columnar is not None:
            return bool(self.columnar)
        return not getattr(self.bus, "faults", None)

    def _publish_columnar(self, t, k, x, sym, n_tracked, nav_due, uav_truth, meas, U, V) -> None:
        """The epoch's UavNav / BeaconMeasurement / Truth of every UAV as UavGroupEpoch messages:
        the same values (UavGroupEpoch.per_uav gives back the messages the per-UAV loop of
        _step_uavs publishes, in its order)."""
        ntr = np.asarray(n_tracked).astype(np.int64)
        fix = np.where(ntr >= 4, 3, np.where(ntr >= 3, 2, 0))
        r = np.asarray(meas.range_m, float)
        ok = r > 0  # a NaN range is not > 0 either
        self.links_nonpositive += int(self.n - np.count_nonzero(ok))
        parts = nav_due * PART_NAV + ok * PART_BEACON + uav_truth * PART_TRUTH
        cols = [np.where(ok, np.asarray(a, float), np.nan) for a in
                (r, meas.range_rate_m_s, meas.var_range_m2, meas.var_range_rate_m2_s2)]
        tp = np.where(uav_truth[:, None], U, np.nan)
        tv = np.where(uav_truth[:, None], V, np.nan)
        for c, (key, gid) in enumerate(self.k_group):
            sl = slice(c * UAV_GROUP_MAX, min(self.n, (c + 1) * UAV_GROUP_MAX))
            if not parts[sl].any():
                continue  # nothing of these UAVs this epoch (the per-UAV path sends nothing either)
            self._publish(key, UavGroupEpoch(
                t_gps_s=t, source_id=gid, seq=k, incarnation=self.inc, group=gid, beacon_id=self.b_id,
                truth_source_id="truth", uav_ids=tuple(self.uav_key_ids[sl]), uav_source_ids=tuple(self.src[sl]),
                parts=parts[sl], n_sats=ntr[sl], fix_type=fix[sl], pos_ecef_m=x[sl, 0:3], vel_ecef_m_s=x[sl, 3:6],
                cov=sym[sl], range_m=cols[0][sl], range_rate_m_s=cols[1][sl], var_range_m2=cols[2][sl],
                var_range_rate_m2_s2=cols[3][sl], truth_pos_ecef_m=tp[sl], truth_vel_ecef_m_s=tv[sl]))

    def _step_sonde(self, t, k) -> None:
        fl = self.flight
        st = fl.state()
        while fl.t_gps_s < t - 1e-6:
            st = fl.step()
        self.last_sonde = st
        pos, vel = st.pos_ecef_m, st.vel_ecef_m_s  # (1, 3)
        if self.with_truth:
            self._publish(self.k_ts, Truth(t_gps_s=t, source_id="truth", seq=k, incarnation=self.inc, kind="sonde", pos_ecef_m=pos[0],
                                           vel_ecef_m_s=vel[0]))
        rt = self.relay.step(t, pos, vel)
        d = rt.delivered[0]
        self.last_relay = int(d.sum())
        self._publish(self.k_relay, SondeRelay(
            t_gps_s=t, source_id="gcpp", seq=k, incarnation=self.inc, sat_ids=rt.sat_id[d],
            pseudorange_m=rt.pseudorange_m[0][d],
            pseudo_doppler_m_s=rt.pseudo_doppler_m_s[0][d], var_pseudorange_m2=rt.var_pr_m2[0][d],
            var_pseudo_doppler_m2_s2=rt.var_prr_m2_s2[0][d], sat_pos_ecef_m=rt.sat_pos_ecef_m[0][d],
            sat_vel_ecef_m_s=rt.sat_vel_ecef_m_s[0][d], ground_pos_ecef_m=rt.ground_pos_ecef_m))
        rm = self.radar.step(t, pos, vel)
        if bool(rm.range_valid[0]):
            self._publish(self.k_radar, RadarMeasurement(
                t_gps_s=t, source_id=self.sonde.radar_id, seq=k, incarnation=self.inc,
                slant_range_m=float(rm.slant_range_m[0]),
                az_rad=float(rm.az_rad[0]), el_rad=float(rm.el_rad[0]), var_range_m2=float(rm.var_range_m2[0]),
                var_az_rad2=float(rm.var_az_rad2[0]), var_el_rad2=float(rm.var_el_rad2[0]),
                angles_valid=bool(rm.angles_valid[0]), radar_pos_ecef_m=rm.site_pos_ecef_m))

    # ------------------------------------------------------------------ checkpoint and resume
    def __getstate__(self) -> dict:
        """Everything but the transport: the world, the sensors' error processes and random
        generators, the onboard filters, the uploaded missions (the worker's checkpoint)."""
        d = dict(self.__dict__)
        d.pop("bus", None)
        d.pop("_uav_nav", None)
        d.pop("endpoints", None)  # the worker's sockets: rebuilt after a resume (build_endpoints)
        d.pop("param_stores", None)
        return d

    def __setstate__(self, d: dict) -> None:
        self.__dict__.update(d)
        self.bus = None
        self.__dict__.setdefault("nav_prior", None)
        self.__dict__.setdefault("last_tracked", None)
        self.__dict__.setdefault("columnar", None)
        if "k_group" not in self.__dict__:  # a checkpoint from before the columnar path
            self._columnar_keys()
        if self.n and "batteries" not in self.__dict__:  # a checkpoint from before the batteries
            self.batteries = self._batteries()
        if self.n:
            from vehicles import uav_nav
            self._uav_nav = uav_nav

    def resume(self, transport, incarnation: int) -> VehicleGroup:
        """A checkpointed group back on a bus, publishing as a new incarnation."""
        self.bus = transport
        self.inc = int(incarnation)
        return self

    def catch_up(self, t_until_gps_s: float) -> int:
        """Step every epoch after the last one up to t_until (included) without publishing: the
        vehicles, their error processes and onboard filters go on as if the worker had never
        stopped (the real vehicles did); what it would have sent meanwhile is lost, as over a
        dead link. Returns the epochs stepped."""
        if self.t_last is None:
            return 0
        dt = 1.0 / self.scn.run.rate_hz
        bus, sent, n = self.bus, self.sent, 0
        self.bus = _Discard()
        try:
            t = self.t_last + dt
            while t <= t_until_gps_s + 1e-9:
                self.step(t)
                t += dt
                n += 1
        finally:
            self.bus, self.sent = bus, sent
        return n

    # ------------------------------------------------------------------ MAVLink side
    def _autopilots(self, scn, in_flight: bool):
        """The group's autopilots (vehicles.autopilot, ArduPlane's convention) over its swarm: each
        UAV in AUTO flying the scenario's pattern (in flight) or disarmed on the ground, home
        where it starts; cruise at [uavs].speed_m_s; detached UAVs integrated at 0.1 s."""
        from vehicles.autopilot import Autopilot, AutopilotConfig, AutopilotSwarm
        st = self.swarm.state
        y = np.asarray(st.y, float).reshape(-1, 4)
        v = float(scn.uavs.speed_m_s)
        base = AutopilotConfig()
        cfg = AutopilotConfig(airspeed_cruise_m_s=v if v > 0 else base.airspeed_cruise_m_s,
                              airspeed_min_m_s=min(base.airspeed_min_m_s, v) if v > 0 else base.airspeed_min_m_s,
                              airspeed_max_m_s=max(base.airspeed_max_m_s, v))
        ap = Autopilot(*y.T, in_flight=in_flight, config=cfg, t0_s=float(st.t_s), ell=self.swarm.ell)
        return AutopilotSwarm(self.swarm, ap, dt_s=0.1)

    def _batteries(self):
        """The UAVs' batteries (vehicles.mavlink.battery.BatteryBank), drawing their cruise current
        at the autopilot's cruise airspeed; capacity each UAV's BATT_CAPACITY, read every step."""
        from vehicles.mavlink.battery import BatteryBank, BatteryParams
        cruise = float(self.fleet.ap.cfgs[0].airspeed_cruise_m_s)
        return BatteryBank(self.n, BatteryParams(cruise_airspeed_m_s=cruise))

    @property
    def autopilot(self):
        """The group's vehicles.autopilot.Autopilot (UAV j = local index j), None without UAVs."""
        return self.fleet.ap if self.fleet is not None else None

    def take_events(self, j: int, seen_epoch: int):
        """(epoch, the last epoch's autopilot events of local UAV j) if newer than seen_epoch."""
        if self.ap_epoch <= seen_epoch:
            return seen_epoch, []
        return self.ap_epoch, [e for e in self.ap_events if e.vehicle == j]

    def on_mission(self, i: int):
        """UAV i's (global index) waypoints [(lat_rad, lon_rad, h_m)] as an AUTO mission (home at
        item 0, NAV_WAYPOINTs at absolute heights), flown from the next epoch; returns the
        autopilot's MissionResult.  (The MAVLink endpoint hands the autopilot the items.)"""
        from pymavlink.dialects.v20 import ardupilotmega as mavlink

        from vehicles.mavlink.mission import MissionItem

        def accept(waypoints):
            j = self.idx.index(i)
            ap = self.fleet.ap
            home = ap.home[j]
            rows = [(home[0], home[1], home[2])] + [tuple(w) for w in waypoints]
            items = [MissionItem(k, mavlink.MAV_FRAME_GLOBAL_INT, mavlink.MAV_CMD_NAV_WAYPOINT, 0, 1, 0.0, 0.0, 0.0,
                                 0.0, int(round(math.degrees(la) * 1e7)), int(round(math.degrees(lo) * 1e7)), float(h))
                     for k, (la, lo, h) in enumerate(rows)]
            res = ap.set_mission(j, items if waypoints else [])
            if res.ok and waypoints:
                from vehicles.autopilot import convention as cv
                ap.set_mode(j, cv.AUTO)
            return res
        return accept

    def on_nav_param(self, store):
        """The parameter store's change callback: the group's receivers and onboard filters take
        the new NavConfig from the next epoch (a bad combination raises ValueError: vetoed)."""
        from vehicles.mavlink.params import apply_uav_params

        def apply(name, value):
            cfg, _ = apply_uav_params(store, nav=self.nav_cfg)
            self.nav_cfg = cfg
            self.nav.config = cfg
        return apply

    def on_uav_param(self, j: int, store, stores: dict):
        """UAV j's (local index) store's change callback: an autopilot parameter configures that
        UAV's autopilot (vehicles.autopilot.config.with_param; a refused combination vetoes);
        SYSID_THISMAV is vetoed (read-only); a navigation parameter applies to the group's
        batch of filters and is mirrored into the group's other stores, which re-announce it."""
        from vehicles.autopilot.config import PARAM_NAMES, with_param
        ap_names = set(PARAM_NAMES.values())
        nav_apply = self.on_nav_param(store)

        def apply(name, value):
            if name == "SYSID_THISMAV":
                raise ValueError("SYSID_THISMAV is read-only: the system id is the UAV's place in its MAVLink block")
            if name in ap_names:
                try:
                    self.fleet.ap.set_config(j, with_param(self.fleet.ap.cfgs[j], name, value))
                except Exception as e:  # filters.params.ParamError and the checks: a veto
                    raise ValueError(str(e)) from None
                return
            nav_apply(name, value)
            eps = getattr(self, "endpoints", None) or {}
            for i, other in stores.items():
                if other is not store:
                    other.assign(name, value)  # the group's value (the simulation took it above)
                    if i in eps:
                        eps[i].announce_param(name)
        return apply

    def telemetry(self) -> list[Telemetry]:
        """Each vehicle's state as its autopilot would report it: the onboard estimate (the
        UAVs' EKF; the sonde's relayed fix is the ground's business, so the truth with the
        receiver's nominal accuracy), attitude from the flight path.

        UAVs: fix_type 3D with >= 3 tracked satellites (the receivers have no clock: three fix
        the position), NO_FIX below; satellites_visible the tracked ones; HDOP / VDOP of the
        tracked satellites' geometry at the estimated position (vehicles.uav_nav.dops_clock_free,
        ephemeris at t, no truth); h_acc / v_acc (eph_m / epv_m) from the onboard EKF's
        covariance rotated to NED at the estimate: sqrt(P_nn + P_ee) (the expected RMS of the
        horizontal error) and sqrt(P_dd); armed and the airspeed from the autopilot's flight;
        ``nav`` the autopilot's guidance (_nav_outputs), ``ekf`` the filter's status
        (_ekf_status)."""
        out = []
        from sitl.geodesy import ecef_to_geodetic
        if self.n and self.last_nav is not None:
            un = self._uav_nav
            est, tu = self.last_nav, self.last_uav_truth
            lat, lon, h = (np.atleast_1d(v) for v in ecef_to_geodetic(est.x[:, 0:3]))
            v = est.x[:, 3:6]  # ECEF -> NED, all UAVs at once
            sl, cl, so, co = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
            ve = -so * v[:, 0] + co * v[:, 1]
            vn = -sl * co * v[:, 0] - sl * so * v[:, 1] + cl * v[:, 2]
            vd = -(cl * co * v[:, 0] + cl * so * v[:, 1] + sl * v[:, 2])
            pitch = np.arctan2(-vd, np.hypot(vn, ve))
            Pp, _ = un.ned_covariances(est)
            eph = np.sqrt(np.maximum(Pp[:, 0, 0] + Pp[:, 1, 1], 0.0))
            epv = np.sqrt(np.maximum(Pp[:, 2, 2], 0.0))
            ntr = est.n_tracked.tolist()
            if self.last_tracked is not None:
                from sitl.gnss.orbits import sat_state_ecef
                sp, _ = sat_state_ecef(self.const, float(est.t_gps_s))
                hd, vdp = un.dops_clock_free(est.x[:, 0:3], sp, self.last_tracked)
            else:
                hd = vdp = np.full(self.n, np.nan)
            hdop = [None if not math.isfinite(x) else x for x in hd.tolist()]
            vdop = [None if not math.isfinite(x) else x for x in vdp.tolist()]
            heading = np.asarray(tu.heading_rad).tolist()
            ap = self.fleet.ap
            armed = ap.armed.tolist()
            air = np.asarray(tu.speed_m_s, float).tolist()
            nav = _nav_outputs(self.fleet, tu)
            ekf = _ekf_status(un, self.nav_prior, est, self.nav_cfg)
            rows = zip(self.idx, lat.tolist(), lon.tolist(), h.tolist(), vn.tolist(), ve.tolist(), vd.tolist(),
                       pitch.tolist(), heading, ntr, eph.tolist(), epv.tolist(), hdop, vdop, armed, air, nav, ekf)
            t = float(est.t_gps_s)
            out.extend(Telemetry("uav", i, t, la, lo, hh, (a, b, c), 0.0, pi, hd_, 3 if nt >= 3 else 1, nt, e1, e2,
                                 hdop=h1, vdop=v1, armed=bool(arm), airspeed_m_s=sp_, nav=nv, ekf=ek)
                       for i, la, lo, hh, a, b, c, pi, hd_, nt, e1, e2, h1, v1, arm, sp_, nv, ek in rows)
        if self.sonde is not None and self.last_sonde is not None:
            st = self.last_sonde
            vn = tuple(float(v) for v in (st.vel_enu_m_s[0][1], st.vel_enu_m_s[0][0], -st.vel_enu_m_s[0][2]))
            sats = self.last_relay or 0
            out.append(Telemetry("sonde", self.scn.uavs.count, float(st.t_gps_s), float(st.lat_rad[0]),
                                 float(st.lon_rad[0]), float(st.alt_m[0]), vn, 0.0, 0.0,
                                 math.atan2(vn[1], vn[0]), 3 if sats >= 4 else 0, sats, 5.0, 8.0))
        return out


def _nav_outputs(fleet, tu) -> list:
    """Each UAV's NAV_CONTROLLER_OUTPUT (vehicles.mavlink.telemetry.NavOutput, SI) from its
    autopilot's guidance of the last step, evaluated at the UAV's state now (the state the
    autopilot steers by): nav_bearing the heading the guidance steers to (GOTO / LAND: the
    target's bearing; ORBIT: the circle's reference heading; LEG / FINAL: the held heading; the
    scenario's own pattern and the ground: the heading now), target_bearing / wp_dist the target
    point's (the loiter's centre for ORBIT; none for LEG, the scenario, the ground), alt_error the
    target altitude - altitude, aspd_error the commanded - flown airspeed, xtrack_error off the
    leg prev -> target (GOTO / LAND) or off the circle (ORBIT, d - r); nav_roll the bank of a
    coordinated turn at the commanded turn rate, atan(v w / g), nav_pitch the commanded flight
    path angle.  None for a UAV in MANUAL (ArduPlane sends none there)."""
    from vehicles.autopilot import convention as cv
    from vehicles.autopilot import guidance as gd
    from vehicles.autopilot.config import G_M_S2
    from vehicles.mavlink.telemetry import NavOutput

    g = fleet.last_guidance
    ap = fleet.ap
    if g is None:
        return [None] * ap.n
    y = fleet.state_y
    lat, lon, h, psi = y[:, 0], y[:, 1], y[:, 2], y[:, 3]
    ell = fleet.swarm.ell
    speed, climb, rate = gd.commands(g, y, ell)  # the scenario's UAVs: zeros (their law is the scenario's)
    kind = np.asarray(g.kind)
    d_e, d_n = gd.offsets(lat, lon, h, g.lat_rad, g.lon_rad, ell)
    d = np.hypot(d_e, d_n)
    brg = np.arctan2(d_e, d_n)
    r = np.maximum(g.radius_m, 1.0)
    ref_orbit = brg - 0.5 * np.pi + np.arctan(gd.K_RADIAL * (d - r) / r)
    goto = (kind == gd.GOTO) | (kind == gd.LAND)
    orbit = kind == gd.ORBIT
    leg = (kind == gd.LEG) | (kind == gd.FINAL)
    pointed = goto | orbit | (kind == gd.FINAL)
    nav_brg = np.where(goto, brg, np.where(orbit, ref_orbit, np.where(leg, g.heading_rad, psi)))
    tgt_brg = np.where(pointed, brg, nav_brg)
    wp = np.where(pointed, d, 0.0)
    flown = np.asarray(tu.speed_m_s, float)
    guided = (kind != gd.SCENARIO) & (kind != gd.HOLD)
    alt_err = np.where(guided, g.alt_m - h, 0.0)
    aspd_err = np.where(guided, g.speed_m_s - flown, 0.0)
    # cross track: the UAV's offset from the leg's start (prev) crossed with the leg's direction
    a_e, a_n = gd.offsets(ap.prev[:, 0], ap.prev[:, 1], ap.prev[:, 2], lat, lon, ell)
    l_e, l_n = gd.offsets(ap.prev[:, 0], ap.prev[:, 1], ap.prev[:, 2], g.lat_rad, g.lon_rad, ell)
    l_len = np.hypot(l_e, l_n)
    with np.errstate(divide="ignore", invalid="ignore"):
        xt_leg = np.where(l_len > 1e-3, (a_n * l_e - a_e * l_n) / l_len, 0.0)
    xtrack = np.where(goto, xt_leg, np.where(orbit, d - r, 0.0))
    v = np.where(guided, np.maximum(speed, 1e-9), flown)
    roll = np.where(guided, np.arctan(v * rate / G_M_S2), 0.0)
    pitch = np.where(guided, np.arcsin(np.clip(climb / np.maximum(v, 1e-9), -1.0, 1.0)), 0.0)
    manual = np.asarray(ap.mode) == cv.MANUAL
    cols = [a.tolist() for a in (roll, pitch, nav_brg, tgt_brg, wp, alt_err, aspd_err, xtrack)]
    return [None if manual[j] else NavOutput(*(c[j] for c in cols)) for j in range(ap.n)]


def _ekf_status(un, prior, est, cfg) -> list:
    """Each UAV's EKF_STATUS_REPORT (vehicles.mavlink.telemetry.EkfStatus): the test ratios of
    the last update (vehicles.uav_nav.innovation_test_ratios; 0 at the initial fix, which has no
    prior); flags: ATTITUDE (from the flight path: known once initialised), and while the
    receiver tracks >= 3 satellites (the filter is aided) horizontal and vertical velocity,
    relative and absolute horizontal position, absolute vertical position and their predicted
    counterparts; with fewer the filter only predicts (no position / velocity flag); GPS_GLITCHING
    while the position or velocity correction fails ArduPilot's 5-sigma gate (ratio > 1)."""
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    from vehicles.mavlink.telemetry import EkfStatus

    n = est.x.shape[0]
    if prior is None or not est.t_gps_s > prior.t_gps_s:
        z = np.zeros(n)
        ratios = (z, z, z)
    else:
        r = un.innovation_test_ratios(prior, est, cfg)
        ratios = tuple(np.nan_to_num(a, nan=0.0) for a in (r.vel, r.pos, r.hgt))
    aided = np.asarray(est.n_tracked) >= 3
    nav_bits = (mavlink.EKF_VELOCITY_HORIZ | mavlink.EKF_VELOCITY_VERT | mavlink.EKF_POS_HORIZ_REL
                | mavlink.EKF_POS_HORIZ_ABS | mavlink.EKF_POS_VERT_ABS | mavlink.EKF_PRED_POS_HORIZ_REL
                | mavlink.EKF_PRED_POS_HORIZ_ABS)
    glitch = (ratios[0] > 1.0) | (ratios[1] > 1.0)
    flags = (mavlink.EKF_ATTITUDE + np.where(aided, nav_bits, 0)
             + np.where(glitch, mavlink.EKF_GPS_GLITCHING, 0)).astype(int).tolist()
    rv, rp, rh = (a.tolist() for a in ratios)
    return [EkfStatus(flags[j], rv[j], rp[j], rh[j]) for j in range(n)]


class _Discard:
    """A transport that drops what is published (VehicleGroup.catch_up)."""

    @staticmethod
    def publish(key, msg) -> None:
        pass


# ---------------------------------------------------------------------- checkpoints (worker)

CHECKPOINT_WALL_S = 1.0  # the worker checkpoints its group at most this often (wall s), after an epoch


def checkpoint_path(spec):
    from pathlib import Path
    return Path(spec.out_dir) / "state" / f"{spec.name}.pkl"


def write_checkpoint(group: VehicleGroup, path) -> None:
    """The group's state, written atomically (a kill -9 in the middle leaves the previous one)."""
    import os
    import pickle
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    with open(tmp, "wb") as f:
        pickle.dump(group, f, protocol=pickle.HIGHEST_PROTOCOL)
    os.replace(tmp, path)


def load_checkpoint(path, spec, scn) -> VehicleGroup | None:
    """The group a previous incarnation of this worker checkpointed (None, with one line on
    stderr saying why, if there is none or it does not belong to this worker and run). The file
    is the run's own, written by this worker in its output directory."""
    import pickle
    try:
        with open(path, "rb") as f:
            g = pickle.load(f)
    except FileNotFoundError:
        return None
    except Exception as e:  # a torn or foreign file: start afresh
        print(f"{spec.name}: checkpoint {path} unreadable ({type(e).__name__}: {e}); cold start", file=sys.stderr)
        return None
    ok = (isinstance(g, VehicleGroup) and g.run_id == spec.run_id and g.idx == list(spec.uav_indices)
          and g.scn.run.seed == scn.run.seed and g.t_last is not None and (g.sonde is not None) == spec.with_sonde)
    if not ok:
        print(f"{spec.name}: checkpoint {path} is not this worker's; cold start", file=sys.stderr)
        return None
    return g


# ---------------------------------------------------------------------- MAVLink glue


def build_endpoints(group: VehicleGroup, scn, out_dir, name: str = "vehicles", *, clock=None, timer=None,
                    epoch_s: float | None = None):
    """vehicles.mavlink endpoints for this group's vehicles: UAV i (global index; the sonde comes
    after the UAVs) gets its MAVLink block's system id, listen port (udp, and tcp with [mavlink]
    tcp, ArduPilot SITL's SERIAL0), GCS address and signing link id from the run's plan
    (sitl.mavlink.blocks: in block 1, sysid i + 1 on base_port + 10 i, to [mavlink] gcs). Parameters:
    the UAV's onboard navigation settings and the sonde's flight model (their real values).
    All the group's traffic goes to one .tlog, OUT/mav_<name>.tlog, stamped by ``clock`` (the
    live worker's wall clock, as MAVProxy's) or else simulated time (a restarted worker starts a
    new file, mav_<name>.r<k>.tlog: nothing recorded is overwritten). With signing, each
    vehicle's signing state is kept in OUT/mav_signing_<sysid>.json (block k >= 2:
    mav_signing_b<k>_<sysid>.json; loaded by a restarted
    worker: a replay of frames captured before the restart stays rejected); clock: the signing
    clock (unix s; the live worker passes the wall clock; None: simulated time); timer: the
    duration clock of the input budget; epoch_s: how often the endpoints are stepped, the fastest a
    stream can go (None: one vehicle epoch, 1 / run.rate_hz). Each UAV endpoint reads its
    autopilot's flight phase (EXTENDED_SYS_STATE) and its battery (BATTERY_STATUS, SYS_STATUS: the
    group's BatteryBank, stepped with the flight). None if MAVLink is off."""
    from pathlib import Path

    from sitl.mavlink.framing import fresh_tlog_path
    from vehicles.mavlink import EndpointGroup, ParamStore, TlogWriter, VehicleEndpoint, load_signing_key
    from vehicles.mavlink.endpoint.handlers import AutopilotPort
    from vehicles.mavlink.params import autopilot_param_specs, sonde_param_specs, uav_param_specs

    from sitl.mavlink.blocks import MavlinkPlan

    m = scn.mavlink
    if not m.enabled:
        return None
    plan = MavlinkPlan.of(scn)
    key = load_signing_key(m.signing_key_file) if m.signing_key_file else None
    vehicles = [("uav", i) for i in group.idx]
    if group.sonde is not None:
        vehicles.append(("sonde", scn.uavs.count))
    tlog = None
    if m.tlog:
        tlog = TlogWriter(fresh_tlog_path(Path(out_dir) / f"mav_{name}.tlog"), stamp_clock=clock)
    # each UAV has its own store: its autopilot's parameters (WP_RADIUS, RTL_ALTITUDE, ...: a set
    # changes that UAV only, from its next step) and SYSID_THISMAV (read-only), and the onboard
    # navigation's (GNSS_*, NAV_Q): the group's filters run as one batch, so a set there applies
    # to the whole group and every UAV of the group re-announces it (PARAM_VALUE); the sonde's
    # flight model is fixed at launch (sets vetoed)
    uav_stores = {}
    for j, i in enumerate(group.idx):
        uav_stores[i] = ParamStore(uav_param_specs(None, group.nav_cfg, 0) + autopilot_param_specs(
            group.autopilot.cfgs[j], sysid=plan.sysid_of(i)))
    for j, i in enumerate(group.idx):
        uav_stores[i].on_change(group.on_uav_param(j, uav_stores[i], uav_stores))
    sonde_store = None
    if group.sonde is not None:
        sonde_store = ParamStore(sonde_param_specs(group.flight.params))
        sonde_store.on_change(_veto_sonde_param)
    eps = []
    try:
        for kind, i in vehicles:
            params = uav_stores[i] if kind == "uav" else sonde_store
            port = AutopilotPort(group, group.idx.index(i)) if kind == "uav" else None
            block, sysid, lport = plan.block_of(i), plan.sysid_of(i), plan.listen_port(i)
            eps.append(VehicleEndpoint(sysid=sysid, kind=kind, gcs=plan.gcs_addr(block), instance=i,
                                       listen=("127.0.0.1", lport), params=params,
                                       tcp_listen=("127.0.0.1", lport) if m.tcp else None,
                                       signing_key=key, tlog=tlog, clock=clock, autopilot=port,
                                       link_id=plan.link_id(block),
                                       signing_state=(Path(out_dir) / plan.signing_state_name(block, sysid)
                                                      if key is not None else None)))
    except Exception:
        for ep in eps:
            ep.close()
        if tlog is not None:
            tlog.close()
        raise
    # the worker steps the endpoints this often: the MAVLink epoch ([mavlink] rate_hz), or the
    # world's when that is faster; epoch_s given (tests) overrides it
    ep_s = 1.0 / max(scn.run.rate_hz, m.rate_hz) if epoch_s is None else float(epoch_s)
    for ep in eps:
        ep.epoch_s = ep_s  # the fastest stream (streams.py)
        if ep.kind == "uav":
            j = group.idx.index(ep.instance)
            ep.landed_state_fn = _landed_state_of(group, j)
            ep.battery = group.batteries.cell(j)
    group.param_stores = uav_stores
    group.endpoints = {ep.instance: ep for ep in eps}  # by global vehicle index
    eg = EndpointGroup(eps, timer=timer)
    eg.tlog_writer = tlog  # shared by the endpoints: closed by the worker after them
    return eg


def _landed_state_of(group: VehicleGroup, j: int):
    """EXTENDED_SYS_STATE.landed_state of local UAV j: its autopilot's flight phase now (on the
    ground, taking off, in the air, landing)."""
    from vehicles.autopilot import convention as cv

    def landed_state() -> int:
        return cv.landed_state(int(group.autopilot.phase[j]))
    return landed_state


#: the share of an epoch's wall time the group's MAVLink input may take (worker main)
_MAV_INPUT_SHARE = 0.25


class _InputService:
    """The worker's MAVLink input between the slices of a world tick: before the world's step,
    between its UAVs' and its sonde's parts (VehicleGroup.step's ``between``) and after it, then
    in the endpoints' own step. A world step at 100 UAVs takes longer than a MAVLink tick on a
    loaded machine; answered only after it, a command waited for the whole step (COMMAND_ACK
    p95 118 ms at 100 UAVs, load 12). The tick's input budget is shared by the calls: each takes
    what the earlier ones of the tick left (``remaining_s``, what the endpoints' step gets)."""

    def __init__(self, endpoints, budget_s: float, timer):
        self.endpoints, self.budget_s, self.timer = endpoints, float(budget_s), timer
        self.t = None
        self.used_s = 0.0
        self.failed: list = []

    def start_tick(self, t_gps_s: float) -> None:
        self.t, self.used_s = float(t_gps_s), 0.0

    def remaining_s(self) -> float:
        return max(0.0, self.budget_s - self.used_s)

    def __call__(self) -> None:
        """Serve the sockets; a failure is kept in ``failed`` (the worker counts and reports it),
        never raised into the world's step."""
        if self.t is None:
            return
        a = self.timer()
        try:
            self.endpoints.serve_input(self.t, self.remaining_s())
        except Exception as e:
            self.failed.append(f"{type(e).__name__}: {e}")
        self.used_s += self.timer() - a

    def take_failed(self) -> list:
        out, self.failed = self.failed, []
        return out


def _mavlink_status(endpoints) -> dict:
    """The status line's ``mavlink`` block: traffic counters; ``datagrams`` (one verdict per
    datagram: accepted + sum(rejected) + kernel_dropped = datagrams sent to the group's ports);
    ``rejected`` the same per-datagram reasons (what the launcher sums as rejected inputs);
    ``frames`` the per-frame rejects (several per datagram possible); ``refused`` valid requests
    refused (unknown parameter, bad mission...)."""
    from vehicles.mavlink.endpoint import FRAME_REJECT_REASONS, PROTOCOL_REJECT_REASONS, TRAFFIC_COUNTERS
    c = endpoints.counters
    dg = endpoints.datagrams
    rej = {r: int(n) for r, n in dg["rejected"].items() if n}
    return {**{k: int(c.get(k, 0)) for k in TRAFFIC_COUNTERS},
            "datagrams": {"accepted": int(dg["accepted"]), "rejected": rej, "kernel_dropped": int(dg["kernel_dropped"])},
            "rejected": dict(rej),
            "frames": {r: int(c[r]) for r in FRAME_REJECT_REASONS if c.get(r)},
            "refused": {r: int(c[r]) for r in PROTOCOL_REJECT_REASONS if c.get(r)}}


def _veto_sonde_param(name, value):
    raise ValueError("the sonde's flight model is fixed at launch")


def turn_rates_rad_s(fleet) -> np.ndarray:
    """(N,) each UAV's heading rate now (rad/s, clockwise from north positive), as its guidance
    commands it: the kinematic model's own psi-dot (vehicles.uav: the heading rate is a
    command), for the UAVs flying the scenario's law and those the autopilot flies."""
    from vehicles.autopilot import guidance as gd
    from vehicles.uav import kinematics as kin
    sw = fleet.swarm
    w = np.zeros(fleet.n)
    own = fleet.own
    if not own.all():
        st = sw.state
        y = np.asarray(st.y, float).reshape(-1, 4)
        _, _, r = kin._commands(sw.guidance, st.t_s, st.y, sw.guidance.target(st, st.t_s), kin.ellipsoid(sw.ell))
        r = np.broadcast_to(np.asarray(r, float).reshape(-1), (y.shape[0],))
        w[~own] = r[~own]
    if own.any() and fleet.last_guidance is not None:
        idx = np.flatnonzero(own)
        law = gd.AutopilotLaw(fleet.last_guidance.subset(idx), fleet._scenario_for(idx), sw.ell)
        _, _, r = kin._commands(law, fleet.t_s, fleet.y[idx], None, kin.ellipsoid(sw.ell))
        w[idx] = np.broadcast_to(np.asarray(r, float).reshape(-1), (idx.size,))
    return w


class SubEpochTelemetry:
    """The vehicles' telemetry at the MAVLink epochs between two world epochs.

    ``reset(tel, turn_rate_rad_s)`` at each world epoch: the group's telemetry (VehicleGroup
    .telemetry: the onboard estimate at that epoch) and each vehicle's heading rate (None or
    0: straight flight); ``at(t_gps_s)`` the same vehicles propagated to t by their motion:
    constant speed and climb, the horizontal velocity turning at the vehicle's heading rate
    (the arc the kinematic model flies while its commands hold) -- what an autopilot's EKF
    reports between two GNSS fixes by dead reckoning, not a held position. At a world epoch
    (t = the telemetry's own time) it is the telemetry unchanged."""

    def __init__(self):
        self.tel: list = []
        self._arr = None

    def reset(self, tel: list, turn_rate_rad_s=None) -> None:
        self.tel = list(tel)
        n = len(self.tel)
        if not n:
            self._arr = None
            return
        w = np.zeros(n)
        if turn_rate_rad_s is not None:
            r = np.asarray(turn_rate_rad_s, float).reshape(-1)
            w[:r.size] = np.where(np.isfinite(r[:n]), r[:n], 0.0)
        v = np.array([tuple(x.vel_ned_m_s) for x in self.tel], float).reshape(n, 3)
        self._arr = (np.array([x.t_gps_s for x in self.tel], float), np.array([x.lat_rad for x in self.tel], float),
                     np.array([x.lon_rad for x in self.tel], float), np.array([x.alt_msl_m for x in self.tel], float),
                     v, np.array([x.yaw_rad for x in self.tel], float), w)

    def at(self, t_gps_s: float) -> list:
        if self._arr is None:
            return []
        t0, lat, lon, h, v, yaw, w = self._arr
        tau = np.maximum(float(t_gps_s) - t0, 0.0)
        if not tau.any():
            return self.tel
        import dataclasses
        a = w * tau
        small = np.abs(a) < 1e-9
        # the horizontal displacement along the arc: integral of R(w s) v0 ds over [0, tau]
        s_ = np.where(small, tau, np.sin(a) / np.where(small, 1.0, w))
        c_ = np.where(small, 0.5 * w * tau * tau, (1.0 - np.cos(a)) / np.where(small, 1.0, w))
        vn, ve, vd = v[:, 0], v[:, 1], v[:, 2]
        dn = vn * s_ - ve * c_
        de = ve * s_ + vn * c_
        ca, sa = np.cos(a), np.sin(a)
        vn1, ve1 = vn * ca - ve * sa, ve * ca + vn * sa
        h1 = h - vd * tau
        # WGS-84 radii of curvature at the epoch's latitude (sub-second steps: the change is nil)
        e2 = 6.69437999014e-3
        sl = np.sin(lat)
        den = np.sqrt(1.0 - e2 * sl * sl)
        rn = 6378137.0 / den
        rm = rn * (1.0 - e2) / (den * den)
        lat1 = lat + dn / (rm + h)
        lon1 = lon + de / ((rn + h) * np.cos(lat))
        lon1 = (lon1 + math.pi) % (2 * math.pi) - math.pi
        yaw1 = yaw + a
        rows = zip(self.tel, tau.tolist(), lat1.tolist(), lon1.tolist(), h1.tolist(), vn1.tolist(), ve1.tolist(),
                   vd.tolist(), yaw1.tolist())
        return [x if ta == 0.0 else dataclasses.replace(x, t_gps_s=x.t_gps_s + ta, lat_rad=la, lon_rad=lo,
                                                       alt_msl_m=hh, vel_ned_m_s=(a_, b_, c_), yaw_rad=yw)
                for x, ta, la, lo, hh, a_, b_, c_, yw in rows]


def _mav_telemetry(tel: list[Telemetry], n_endpoints: int):
    from vehicles.mavlink import VehicleTelemetry
    out = []
    for v in tel:
        out.append(VehicleTelemetry(lat_rad=v.lat_rad, lon_rad=v.lon_rad, alt_msl_m=v.alt_msl_m,
                                    vel_ned_m_s=tuple(v.vel_ned_m_s), roll_rad=v.roll_rad, pitch_rad=v.pitch_rad,
                                    yaw_rad=v.yaw_rad, fix_type=v.fix_type, satellites_visible=v.satellites_visible,
                                    eph_m=v.eph_m, epv_m=v.epv_m, hdop=v.hdop, vdop=v.vdop, armed=v.armed,
                                    airspeed_m_s=v.airspeed_m_s, nav=v.nav, ekf=v.ekf))
    return (out + [None] * n_endpoints)[:n_endpoints]


# ---------------------------------------------------------------------- worker main


def main(argv=None) -> int:
    from sitl.live.worker import WorkerRuntime, open_bus

    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 1:
        print("usage: python -m vehicles.process SPEC.json", file=sys.stderr)
        return 2
    rt = WorkerRuntime(argv[0])
    spec, scn = rt.spec, rt.scenario
    from sitl.pacing import perf_now, thread_cpu_now
    bus = _TimedPublish(open_bus(spec, scn.bus.lease_ms), perf_now)
    endpoints = None
    try:
        # a restarted worker resumes its previous incarnation's checkpoint (the simulator died,
        # not the vehicles: their flight, sensors and onboard filters go on); else a fresh group
        ckpt = checkpoint_path(spec)
        group = load_checkpoint(ckpt, spec, scn) if rt.incarnation > 0 else None
        resumed = group is not None
        if resumed:
            group.resume(bus, rt.incarnation)
        else:
            seq = np.random.SeedSequence([scn.run.seed, 1000 + spec.group_index])
            group = VehicleGroup(scn, spec.uav_indices, bus, seq, with_beacon_truth=spec.with_beacon_truth,
                                 with_sonde=spec.with_sonde, incarnation=rt.incarnation)
        _warm_up(scn, spec)
        from sitl.pacing import wall_now
        try:  # the composition root: signing follows the wall clock, the input budget is wall time
            endpoints = build_endpoints(group, scn, spec.out_dir, spec.name, clock=wall_now, timer=perf_now)
        except (ValueError, OSError) as e:  # a port taken, a bad key file: a configuration error
            rt.emit({"event": "fatal", "error": f"MAVLink: {' '.join(str(e).split())}"})
            return 2
        if not rt.wait_start():
            return 0
        pacer = rt.pacer()
        dt = 1.0 / scn.run.rate_hz
        t0 = scn.run.t0_gps_s
        t_end = t0 + scn.run.duration_s
        # a (re)started group joins at the current epoch
        k0 = max(0, math.ceil((pacer.sim_now() - t0) / dt - 1e-9))
        if resumed:  # the world through the gap, unpublished (VehicleGroup.catch_up)
            k0 = max(k0, round((group.t_last - t0) / dt) + 1)
            caught = group.catch_up(t0 + (k0 - 1) * dt)
            print(f"{spec.name}: resumed from the checkpoint of t = {group.t_last - caught * dt - t0:.1f} s, "
                  f"{caught} epochs caught up", file=sys.stderr)
        t_first = t0 + k0 * dt
        next_ckpt = 0.0
        errors = 0
        from collections import deque
        # the loop's tick: the MAVLink epoch ([mavlink] rate_hz, at least the world's), so that
        # replies wait at most one MAVLink epoch and streams run up to its rate; the world (its
        # measurements, the bus) steps at its own epochs t0 + k / run.rate_hz, each at the first
        # tick at or after it; between them the endpoints report the vehicles propagated
        dt_tick = dt if endpoints is None else min(dt, 1.0 / scn.mavlink.rate_hz)
        # MAVLink input may take this share of a tick's wall time, shared over the group's
        # sockets (what does not fit waits in the kernel queue; what overflows it is counted)
        mav_budget_s = _MAV_INPUT_SHARE * dt_tick / scn.run.speed
        serve = _InputService(endpoints, mav_budget_s, perf_now) if endpoints is not None else None
        step_s = deque(maxlen=2000)  # wall time of each world epoch's tick (world + bus + MAVLink)
        # where a world tick's time goes (the status line's tick_parts_ms): MAVLink input served,
        # the world's step without it, the bus puts inside that step, the MAVLink streams, and the
        # thread's CPU time over the tick (a wall p99 far above the CPU p99 is waiting, not work)
        parts = {name: deque(maxlen=2000) for name in TICK_PARTS}
        mav_s = deque(maxlen=2000)  # wall time of each tick between them (MAVLink only)
        k_next = k0  # the next world epoch, t0 + k_next dt
        pace = {"late_epochs": 0, "skipped_epochs": 0, "shed_mavlink_ticks": 0}  # world epochs late; jumped over
        sub = SubEpochTelemetry()
        for t in pacer.epochs(t_first, dt_tick, t_end, max_lag_s=5 * dt):
            w0, c0 = perf_now(), thread_cpu_now()
            world = t >= t0 + k_next * dt - 1e-6
            if not world and pacer.sim_now() - t > dt_tick:
                # behind by more than a tick (a loaded machine): a MAVLink-only tick is best
                # effort and is shed, so the world's epochs (measurements, the bus) catch up
                # instead of falling past the pacer's lag limit and being lost
                pace["shed_mavlink_ticks"] += 1
                continue
            if world:
                k = max(k_next, math.floor((t - t0) / dt + 1e-6))  # the latest due (skipped ones: lost)
                tw = t0 + k * dt
                if k_next > k0:  # the status line's late / skipped epochs are the world's
                    pace["skipped_epochs"] += k - k_next
                pace["late_epochs"] += pacer.sim_now() - tw > dt
                k_next = k + 1
                if serve is not None:  # what came in while the loop waited: answered before the world's step
                    serve.start_tick(t)
                    serve()
                s0, u0, b0 = perf_now(), serve.used_s if serve is not None else 0.0, bus.publish_s
                try:
                    group.step(tw, between=serve)
                except Exception as e:  # one bad epoch must not end the run: counted, reported
                    errors += 1
                    if errors <= 10 or errors % 100 == 0:  # the log stays readable
                        print(f"{spec.name}: epoch {tw:.3f} failed ({errors} so far): {type(e).__name__}: {e}",
                              file=sys.stderr)
                in_step = (serve.used_s if serve is not None else 0.0) - u0
                parts["world"].append(perf_now() - s0 - in_step)
                parts["bus_put"].append(bus.publish_s - b0)
                if serve is not None:
                    serve()
                    for text in serve.take_failed():
                        errors += 1
                        if errors <= 10 or errors % 100 == 0:
                            print(f"{spec.name}: MAVLink input failed ({errors} so far): {text}", file=sys.stderr)
            m0 = perf_now()
            if endpoints is not None:
                try:
                    if world:
                        sub.reset(group.telemetry(), turn_rates_rad_s(group.fleet) if group.fleet is not None
                                  else None)
                    endpoints.step(t, _mav_telemetry(sub.at(t), len(endpoints)),
                                   budget_s=serve.remaining_s() if world else mav_budget_s)
                except Exception as e:
                    errors += 1
                    if errors <= 10 or errors % 100 == 0:
                        print(f"{spec.name}: MAVLink step failed ({errors} so far): {type(e).__name__}: {e}",
                              file=sys.stderr)
            (step_s if world else mav_s).append(perf_now() - w0)
            if world:
                parts["streams"].append(perf_now() - m0)
                parts["input"].append(serve.used_s if serve is not None else 0.0)
                parts["cpu"].append(thread_cpu_now() - c0)
            if world and perf_now() >= next_ckpt and group.t_last is not None:
                next_ckpt = perf_now() + CHECKPOINT_WALL_S
                try:
                    write_checkpoint(group, ckpt)
                except OSError as e:  # the run goes on; a restart would cold-start
                    print(f"{spec.name}: checkpoint not written: {e}", file=sys.stderr)
            if rt.status_due():
                rt.emit(_status(group, bus, pacer, endpoints, errors, t, step_s, mav_s, pace, parts))
        rt.emit({**_status(group, bus, pacer, endpoints, errors, group.t_last, step_s, mav_s, pace, parts),
                 "event": "done"})
        return 0
    finally:
        if endpoints is not None:
            endpoints.close()
            if endpoints.tlog_writer is not None:
                endpoints.tlog_writer.close()
        bus.close()


def _warm_up(scn, spec) -> None:
    """Two epochs of a throwaway copy on an in-memory bus: the first epoch's one-off costs
    (kernel loading, ephemeris tables) are paid before the run starts, not in its first epochs."""
    from sitl.bus import InMemoryTransport
    bus = InMemoryTransport()
    if scn.mavlink.enabled:
        from vehicles.mavlink.endpoint import batch
        batch.warm()
    g = VehicleGroup(scn, spec.uav_indices[:3], bus, np.random.SeedSequence(0), with_sonde=spec.with_sonde)
    for k in range(2):
        g.step(scn.run.t0_gps_s + k / scn.run.rate_hz)
    bus.close()


#: the parts of a world tick the worker times (the status line's ``tick_parts_ms``): ``input``
#: MAVLink input served (before, inside and after the world's step), ``world`` the world's step
#: without that input, ``bus_put`` the bus publishes inside it (encode + put), ``streams`` the
#: MAVLink streams and replies after it, ``cpu`` the worker thread's CPU time over the whole tick
TICK_PARTS = ("input", "world", "bus_put", "streams", "cpu")


class _TimedPublish:
    """The worker's bus with its publishes timed (``publish_s``, summed): the tick breakdown's
    ``bus_put``. Everything else is the bus's own."""

    def __init__(self, bus, timer):
        self._bus, self._timer, self.publish_s = bus, timer, 0.0

    def publish(self, key, msg):
        a = self._timer()
        try:
            return self._bus.publish(key, msg)
        finally:
            self.publish_s += self._timer() - a

    def __getattr__(self, name):
        return getattr(self._bus, name)


def _pcts_ms(xs) -> dict:
    a = np.sort(np.array(xs))
    return {"p50": 1e3 * float(a[len(a) // 2]), "p99": 1e3 * float(a[min(len(a) - 1, int(0.99 * len(a)))]),
            "max": 1e3 * float(a[-1])}


def _status(group, bus, pacer, endpoints, errors, t, step_s=(), mav_s=(), pace=None, parts=None) -> dict:
    """The worker's status line. pace: the world epochs' late / skipped counts (the pacer's
    count the loop's ticks: ``late_ticks``, ``skipped_ticks``); parts: TICK_PARTS' samples."""
    from sitl.pacing import cpu_now
    from sitl.live.worker import bus_counters
    d = {"event": "status", "t_sim_s": t, "cpu_s": cpu_now(), "epochs": group.epoch, "vehicles": group.n + (group.sonde is not None),
         "uavs": group.n, "lag_s": max(0.0, pacer.sim_now() - (t or 0.0)), "late_epochs": pacer.late_epochs,
         "skipped_epochs": pacer.skipped_epochs, "step_errors": errors, **bus_counters(bus)}
    if pace is not None:
        d.update(late_ticks=pacer.late_epochs, skipped_ticks=pacer.skipped_epochs, **pace)
    if endpoints is not None:
        d["mavlink"] = _mavlink_status(endpoints)
    for name, xs in (("step_ms", step_s), ("mav_step_ms", mav_s)):  # world epochs; MAVLink-only ticks
        if xs:
            d[name] = _pcts_ms(xs)
    if parts and any(parts.values()):
        d["tick_parts_ms"] = {name: _pcts_ms(xs) for name, xs in parts.items() if xs}
    return d


if __name__ == "__main__":
    sys.exit(main())
