"""MAVLink networks ("blocks") for swarms larger than one network's system ids: which vehicle
gets which (block, system id), each block's GCS address and each vehicle's ports.

One MAVLink network has system ids 1..255; a GCS tells vehicles apart by system id alone, so a
network holds at most 249 vehicles here (250 is the ground station, 255 the GCS: MAVProxy's and
QGroundControl's own id).  Real fleets beyond that run several networks, one GCS link each;
this is that convention:

* vehicles are numbered 1..N in the run (the UAVs in order, then the sonde: the number the
  fault links ``mav:N`` use) and cut into blocks of ``block_size`` consecutive vehicles
  ([mavlink] block_size, at most 249): vehicle v (1-based) is in block k = (v - 1) // block_size + 1
  with system id (v - 1) % block_size + 1 -- block 1 is the single network of a run up to 249
  vehicles, unchanged;
* block k's GCS address is [mavlink] gcs's host and its port + gcs_port_step (k - 1): 14550,
  14560, 14570, ... by default (the ports ArduPilot's sim_vehicle.py gives MAVProxy's output of
  instances 0, 1, 2, ...); every vehicle of block k sends there, and a GCS on that port sees
  exactly block k's vehicles.  gcs_port_step = 0 sends every block to the one address (for a
  router or proxy that tells blocks apart by source address, as the launcher's fault front does);
* the vehicle with system id s in block k listens on UDP -- and TCP with [mavlink] tcp, as
  ArduPilot SITL's SERIAL0 -- port base_port + (k - 1) + 10 (s - 1).  Block 1 is ArduPilot SITL's
  instance layout (instance s - 1 at 5760 + 10 (s - 1)); block k the same layout moved up by
  k - 1, in the ports ArduPilot's instances leave between their SERIAL ports.  So a port says
  its vehicle: (port - base_port) // 10 + 1 is the system id, (port - base_port) % 10 + 1 the
  block; all of a run's vehicle ports lie in base_port .. base_port + 10 block_size - 1
  (5760..8249 by default, whatever the swarm: far below the GCS ports and the kernel's
  ephemeral range 32768..60999 that the Zenoh router's "any free port" draws from), and at most
  MAX_MAVLINK_BLOCKS = 10 blocks (2,490 vehicles) have ports;
* the ground station (system 250) is a component of every block: its HEARTBEAT, ADSB_VEHICLE /
  UTM_GLOBAL_POSITION of every estimated object and its STATUSTEXT go to every block's GCS
  address, each block its own MAVLink stream (sequence numbers) -- a GCS on any block sees the
  ground station and the estimates;
* signing: one key for the fleet ([mavlink] signing_key_file); block k's frames (vehicles' and
  the ground station's) are signed on link id k - 1, and every (block, system id) keeps its own
  signing state (OUT/mav_signing_<sysid>.json in block 1, OUT/mav_signing_b<k>_<sysid>.json in
  block k >= 2), so the networks' timestamp streams never meet;
* ``--instance N`` adds 10 N to base_port, to the GCS port (so to every block's) and to the
  router's listen port, as ArduPilot SITL's ``-I N``; two runs side by side do not collide when
  their instances differ by at least the other's vehicles per block (vehicle ports) and its
  block count (GCS ports); the launcher's preflight names a port that is taken.

Pure arithmetic: no sockets.  The scenario validates a plan (``MavlinkPlan.problems``) and the
launcher, the vehicle workers, the ground station, the fault proxies and `skyfuse bench live`
all read their addresses from it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from sitl.constants import MAX_MAVLINK_BLOCKS, MAX_MAVLINK_VEHICLES

#: the stride of a block's vehicle ports (ArduPilot SITL's instance stride)
PORT_STRIDE = 10
GS_SYSID = 250
_LOOPBACK = ("127.", "localhost", "0.0.0.0", "::1")


@dataclass(frozen=True)
class MavlinkPlan:
    """The (block, system id) and ports of every vehicle of a run (module docstring).
    Vehicles are indexed 0..n_vehicles - 1 (``index``: the vehicle number - 1); blocks from 1."""

    n_vehicles: int
    gcs_host: str = "127.0.0.1"
    gcs_port: int = 14550
    gcs_port_step: int = 10
    base_port: int = 5760
    block_size: int = MAX_MAVLINK_VEHICLES

    @classmethod
    def of(cls, scn) -> MavlinkPlan:
        """The plan of a scenario (sitl.scenario.Scenario: its [mavlink] section and vehicles)."""
        m = scn.mavlink
        host, _, port = m.gcs.rpartition(":")
        return cls(n_vehicles=scn.n_vehicles, gcs_host=host, gcs_port=int(port), gcs_port_step=m.gcs_port_step,
                   base_port=m.base_port, block_size=m.block_size)

    # ------------------------------------------------------------------ blocks
    @property
    def n_blocks(self) -> int:
        """Blocks with a vehicle (at least 1: the ground station's network exists without one)."""
        return max(1, math.ceil(self.n_vehicles / self.block_size))

    def block_of(self, index: int) -> int:
        return int(index) // self.block_size + 1

    def sysid_of(self, index: int) -> int:
        return int(index) % self.block_size + 1

    def link_id(self, block: int) -> int:
        """The signing link id of block ``block``'s frames."""
        return int(block) - 1

    def indices(self, block: int) -> range:
        """The vehicle indices of block ``block``."""
        lo = (int(block) - 1) * self.block_size
        return range(lo, min(self.n_vehicles, lo + self.block_size))

    def index_of(self, block: int, sysid: int) -> int:
        return (int(block) - 1) * self.block_size + int(sysid) - 1

    # ------------------------------------------------------------------ addresses
    def listen_port(self, index: int) -> int:
        """The vehicle's UDP (and TCP) port: base_port + (block - 1) + 10 (sysid - 1)."""
        return self.base_port + (self.block_of(index) - 1) + PORT_STRIDE * (self.sysid_of(index) - 1)

    def gcs_addr(self, block: int) -> tuple[str, int]:
        return self.gcs_host, self.gcs_port + self.gcs_port_step * (int(block) - 1)

    def gcs_addrs(self) -> list[tuple[str, int]]:
        """Every block's GCS address, block 1 first (the ground station sends to each)."""
        return [self.gcs_addr(k) for k in range(1, self.n_blocks + 1)]

    def vehicle_at_port(self, port: int) -> int | None:
        """The index of the vehicle listening on ``port``, or None."""
        d = int(port) - self.base_port
        if d < 0:
            return None
        block, sysid = d % PORT_STRIDE + 1, d // PORT_STRIDE + 1
        if block > self.n_blocks or sysid > self.block_size:
            return None
        i = self.index_of(block, sysid)
        return i if i < self.n_vehicles else None

    def signing_state_name(self, block: int, sysid: int) -> str:
        """The file (in the run's output directory) of (block, sysid)'s signing state."""
        return f"mav_signing_{sysid}.json" if int(block) == 1 else f"mav_signing_b{int(block)}_{sysid}.json"

    def describe(self, index: int) -> str:
        """E.g. "vehicle 260 (block 2, system id 11)"."""
        return f"vehicle {index + 1} (block {self.block_of(index)}, system id {self.sysid_of(index)})"

    # ------------------------------------------------------------------ checks
    def problems(self, bus_listen_port: int | None = None, tcp: bool = True) -> list[tuple[str, str]]:
        """What makes the plan unusable, as (scenario key, one-line expectation) pairs: too many
        blocks, a port beyond 65535, a block's GCS port (on a local host) that is also a vehicle's
        port, the embedded router's fixed TCP listen port on a vehicle's TCP port."""
        out = []
        if self.n_blocks > MAX_MAVLINK_BLOCKS:
            out.append(("uavs.count", f"expected at most {MAX_MAVLINK_BLOCKS} x mavlink.block_size = "
                                      f"{MAX_MAVLINK_BLOCKS * self.block_size} vehicles (UAVs + sonde) with "
                                      f"mavlink.enabled (at most {MAX_MAVLINK_BLOCKS} MAVLink blocks: block k's "
                                      f"vehicles listen on base_port + (k - 1) + 10 j), got {self.n_vehicles}; "
                                      + (f"raise mavlink.block_size (at most {MAX_MAVLINK_VEHICLES}), or "
                                         if self.block_size < MAX_MAVLINK_VEHICLES else "")
                                      + "set mavlink.enabled = false"))
            return out
        top = self.base_port + PORT_STRIDE * (min(self.n_vehicles, self.block_size) - 1) + self.n_blocks - 1
        if top > 65535:
            out.append(("mavlink.base_port", f"expected every vehicle port (base_port + (block - 1) + 10 (sysid - 1)) "
                                             f"<= 65535, got {top} with base_port = {self.base_port}"))
        gtop = self.gcs_addr(self.n_blocks)[1]
        if gtop > 65535:
            out.append(("mavlink.gcs", f"expected every block's GCS port (the gcs port + gcs_port_step (block - 1)) "
                                       f"<= 65535, got {gtop} for block {self.n_blocks}"))
        if not out and self.gcs_host.startswith(_LOOPBACK):
            for k in range(1, self.n_blocks + 1):
                i = self.vehicle_at_port(self.gcs_addr(k)[1])
                if i is not None:
                    out.append(("mavlink.gcs", f"expected block {k}'s GCS port {self.gcs_addr(k)[1]} to be no "
                                               f"vehicle's port, but {self.describe(i)} listens there (vehicle ports: "
                                               f"base_port {self.base_port} + (block - 1) + 10 (sysid - 1)); move "
                                               "mavlink.base_port or mavlink.gcs"))
                    break
        if not out and tcp and bus_listen_port:
            i = self.vehicle_at_port(bus_listen_port)
            if i is not None:
                out.append(("bus.listen", f"expected a TCP port that is no vehicle's (mavlink.tcp: {self.describe(i)} "
                                          f"serves TCP {bus_listen_port}); port 0 takes any free one"))
        return out


__all__ = ["GS_SYSID", "PORT_STRIDE", "MavlinkPlan"]
