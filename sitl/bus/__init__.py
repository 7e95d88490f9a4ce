"""The message bus: one versioned schema, one codec, two transports (`InMemoryTransport` for
batch runs; `ZenohTransport` for live runs, through an embedded `Router`), and the
crash-safe bus log (`BusLogWriter`, `read_bus_log`, `BusRecorder`).

    from sitl.bus import InMemoryTransport, UavNav, key_for
    bus = InMemoryTransport()
    bus.subscribe("run1/uav/*/nav", lambda key, msg: ...)
    bus.publish(key_for("run1", nav, uav=3), nav)
    bus.drain(t_gps_s)
"""

from .buslog import (
    BusLogError,
    BusLogStats,
    BusLogWriter,
    BusRecord,
    BusRecorder,
    read_bus_log,
    read_bus_log_records,
)
from .codec import MAX_PAYLOAD_BYTES, BusDecodeError, decode, encode, pack_sealed
from .linkstats import LinkMonitor, LinkState
from .router import Router, RouterError
from .schema import (
    KEY_TEMPLATES,
    KINDS,
    MESSAGE_TYPES,
    SCHEMA_VERSION,
    BeaconMeasurement,
    Estimate,
    FaultControl,
    IntegrityEvent,
    LinkStats,
    Message,
    RadarMeasurement,
    SchemaError,
    SondeRelay,
    Truth,
    UavGroupEpoch,
    UavNav,
    check_id,
    is_valid_id,
    key_for,
    key_pattern,
    parse_key,
)
from .transport import (
    InMemoryTransport,
    KeyExprError,
    LinkCounters,
    SeqCounters,
    SeqResult,
    SequenceTracker,
    Subscription,
    Transport,
    TransportStats,
    key_matches,
    validate_key,
    validate_key_expr,
)
from .zenoh_transport import ZenohConfigError, ZenohTransport, ZenohTransportError

__all__ = [
    "KEY_TEMPLATES",
    "KINDS",
    "MAX_PAYLOAD_BYTES",
    "MESSAGE_TYPES",
    "SCHEMA_VERSION",
    "BeaconMeasurement",
    "BusDecodeError",
    "BusLogError",
    "BusLogStats",
    "BusLogWriter",
    "BusRecord",
    "BusRecorder",
    "Estimate",
    "FaultControl",
    "InMemoryTransport",
    "IntegrityEvent",
    "KeyExprError",
    "LinkCounters",
    "LinkMonitor",
    "LinkState",
    "LinkStats",
    "Message",
    "RadarMeasurement",
    "Router",
    "RouterError",
    "SchemaError",
    "SeqCounters",
    "SeqResult",
    "SequenceTracker",
    "SondeRelay",
    "Subscription",
    "Transport",
    "TransportStats",
    "Truth",
    "UavGroupEpoch",
    "UavNav",
    "ZenohConfigError",
    "ZenohTransport",
    "ZenohTransportError",
    "check_id",
    "decode",
    "encode",
    "is_valid_id",
    "key_for",
    "key_matches",
    "key_pattern",
    "pack_sealed",
    "parse_key",
    "read_bus_log",
    "read_bus_log_records",
    "validate_key",
    "validate_key_expr",
]
