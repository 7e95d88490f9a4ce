"""The MAVLink wire, shared by the vehicles' endpoints and the ground station's output: framing
of UDP datagrams, MAVLink 2 signing (keys, checks, the persisted signing state) and .tlog
files (framing.py). Byte-level, no sockets, no vehicle behaviour (that is vehicles.mavlink)."""
