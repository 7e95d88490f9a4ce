"""Network fault injection: netem-like fault models in simulation time.

``from sitl.netfault import FaultSpec, FaultSpecError, parse_spec, LinkFault, LinkTruth,
KeyFaults`` -- see `sitl.netfault.spec` (the text grammar) and `sitl.netfault.models`
(the models, their netem equivalents and what the tests check).
"""
from .models import KeyFaults, LinkFault, LinkTruth
from .spec import FaultSpec, FaultSpecError, parse_spec

__all__ = ["FaultSpec", "FaultSpecError", "KeyFaults", "LinkFault", "LinkTruth", "parse_spec"]
