"""The radiosonde tracker of the ground station (Moroz et al., seed 004): relayed GNSS fused with
an aerological radar. One module a concern: params (parameters, state layout), transition (the
sonde's motion), measurements (the relay and radar rows), relay_fix (the relay least-squares fix),
relay_errors (the relay's per-satellite error states), epoch_model, update, window, initialise,
landing, integrity, history (the lag window), counters, and tracker (SondeTracker on the bus)."""
from .counters import TrackerCounters
from .measurements import SondeMeasurement, relay_frame_point, wrap_pi
from .params import KINEMATICS, MODES, RADAR_NOISE, Layout, SondeTrackerParams, layout_for
from .relay_fix import RelayFix, relay_fix
from .tracker import SondeTracker
from .transition import SondeTransition, descent_speed, relaxed_axis_discretisation

__all__ = [
    "KINEMATICS",
    "MODES",
    "RADAR_NOISE",
    "Layout",
    "RelayFix",
    "SondeMeasurement",
    "SondeTracker",
    "SondeTrackerParams",
    "SondeTransition",
    "TrackerCounters",
    "descent_speed",
    "layout_for",
    "relaxed_axis_discretisation",
    "relay_fix",
    "relay_frame_point",
    "wrap_pi",
]
