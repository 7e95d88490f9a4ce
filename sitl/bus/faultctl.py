"""The network-fault control key of a live run: `skyfuse fault` publishes a FaultControl request
on ``<run>/ctl/fault``; the launcher applies it through its fault board and answers on
``<run>/ctl/fault/ack`` with the same seq (a repeated request is answered, not re-applied).
The keys, the request loop (`serve`) and the board of a run without faults. Light: no numpy, no
fault models (a run without faults does not load them; sitl.netfault.control is the board of
a run with faults)."""
from __future__ import annotations

from collections import Counter
from collections.abc import Callable

CTL_SUFFIX = "ctl/fault"
ACK_SUFFIX = "ctl/fault/ack"
LIST_LINK = "?"
ERROR_PREFIX = "error: "
NO_FAULTS = ("this run has no [faults] table; start it with one (an empty [faults] is enough) "
             "to change faults at run time")


def control_key(run_id: str) -> str:
    return f"{run_id}/{CTL_SUFFIX}"


def ack_key(run_id: str) -> str:
    return f"{run_id}/{ACK_SUFFIX}"


class NoFaultBoard:
    """The board of a run without [faults]: no links; every change is refused (counted)."""

    def __init__(self):
        self.links: dict = {}
        self.bad: Counter = Counter()
        self.requests = 0
        self.on_change: Callable[[], None] | None = None

    def current(self) -> dict:
        return {}

    def handle(self, msg) -> tuple[bool, str]:
        self.requests += 1
        if msg.link == LIST_LINK:
            return True, "{}"
        self.bad["no faults in this run"] += 1
        return False, NO_FAULTS

    def report(self) -> dict:
        return {"links": {}, "requests": self.requests, "bad_requests": dict(self.bad), "errors": []}


def serve(board, bus, run_id: str, *, on_line: Callable[[str], None] | None = None):
    """Subscribe the launcher's bus to the control key: each request is applied through the
    board and acknowledged on the ack key (same seq). Returns the subscription (queue mode:
    requests are handled when the launcher drains its bus)."""
    from collections import OrderedDict

    from sitl.bus.schema import FaultControl
    done: OrderedDict = OrderedDict()  # (source_id, seq) -> answer: a repeated request is answered, not re-applied

    def on_request(key: str, msg) -> None:
        if not isinstance(msg, FaultControl) or key != control_key(run_id):
            return
        rid = (msg.source_id, msg.seq)
        if rid in done:
            reply = done[rid]
        else:
            ok, text = board.handle(msg)
            if on_line is not None and msg.link != LIST_LINK:
                on_line(f"[fault] {msg.link} = {text}" if ok else f"[fault] refused {msg.link!r}: {text}")
            reply = text if ok else ERROR_PREFIX + text
            done[rid] = reply
            while len(done) > 256:
                done.popitem(last=False)
        try:
            bus.publish(ack_key(run_id), FaultControl(t_gps_s=msg.t_gps_s, source_id="launcher", seq=msg.seq,
                                                      link=msg.link, spec=reply[:1000]))
        except Exception as e:  # the answer is best effort; the change is applied and logged
            board.bad["ack failed"] += 1
            if on_line is not None:
                on_line(f"[fault] ack failed: {type(e).__name__}: {e}")

    return bus.subscribe(control_key(run_id), on_request)
