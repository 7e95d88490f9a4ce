"""Many vehicle endpoints stepped together in one process: one selector poll per step, the
input budget shared over the sockets, the counters summed."""
from __future__ import annotations

import selectors
import time
from typing import Callable, Iterable, Sequence

from ..telemetry import VehicleTelemetry
from .batch import StreamBatch
from .constants import DATAGRAM_REJECT_REASONS
from .receive import _drain
from .vehicle import VehicleEndpoint


class EndpointGroup:
    """Many endpoints stepped together: one selector (epoll) poll per step over all sockets
    (UDP sockets and TCP listeners; the TCP clients of the endpoints that have some are read
    every step).

    ``step(t_gps_s, telemetry_list, budget_s=None)``: telemetry_list[i] (or None) for
    endpoints[i]; the streams due go out framed together, each endpoint's frames of the step
    packed into few datagrams (batch.py; ``batch_streams=False``: pymavlink's frame per datagram); budget_s: the wall seconds the group's input may take this step, shared over
    the sockets that have input (None: every socket read until it is empty).  timer: the
    duration clock the budget is measured with (seconds; default time.perf_counter).
    ``counters``, ``datagrams``: the endpoints' summed.
    """

    def __init__(self, endpoints: Iterable[VehicleEndpoint], *, timer: Callable[[], float] | None = None,
                 batch_streams: bool = True):
        self.endpoints = list(endpoints)
        # the streams of a step framed together and each endpoint's packed into few datagrams
        # (batch.py); False: each frame by pymavlink in its own datagram (the bench's peer)
        self.batch_streams = bool(batch_streams)
        # one system id per MAVLink network: a group may span blocks (sitl.mavlink.blocks), whose
        # system ids repeat, each block on its own link id
        ids = [(ep.link_id, ep.sysid) for ep in self.endpoints]
        if len(set(ids)) != len(ids):
            raise ValueError(f"endpoints must have distinct system ids per link id, got {ids}")
        self._timer = time.perf_counter if timer is None else timer
        self._round = 0
        self._sel = selectors.DefaultSelector()
        for ep in self.endpoints:
            self._sel.register(ep.sock, selectors.EVENT_READ, ep)
        self._tcp = [ep for ep in self.endpoints if getattr(ep, "tcp", None) is not None]
        for ep in self._tcp:  # the TCP listeners (data: a tuple, to tell them from the UDP sockets)
            self._sel.register(ep.tcp.sock, selectors.EVENT_READ, (ep,))

    def __len__(self) -> int:
        return len(self.endpoints)

    def step(self, t_gps_s: float, telemetry_list: Sequence[VehicleTelemetry | None],
             budget_s: float | None = None) -> None:
        if len(telemetry_list) != len(self.endpoints):
            raise ValueError(f"telemetry_list must have one entry per endpoint ({len(self.endpoints)}), "
                             f"got {len(telemetry_list)}")
        self.serve_input(t_gps_s, budget_s)
        batch = StreamBatch() if self.batch_streams else None
        try:
            for ep, tel in zip(self.endpoints, telemetry_list):
                ep._advance(tel, batch)
        finally:
            if batch is not None:
                batch.flush()

    def serve_input(self, t_gps_s: float, budget_s: float | None = None) -> None:
        """Only the input half of `step`: handle what arrived (replies go out at once) at
        simulated time t_gps_s, sending no stream. The worker calls it between the slices of a
        long world step, so a command waits for the next slice, not for the whole step."""
        if budget_s is not None and not (isinstance(budget_s, (int, float)) and budget_s >= 0):
            raise ValueError(f"budget_s must be None or >= 0 s, got {budget_s!r}")
        for ep in self.endpoints:
            ep._update_clock(t_gps_s)
        keys = [key.data for key, _ in self._sel.select(0)]
        ready = [d for d in keys if not isinstance(d, tuple)]
        if ready:
            _drain(ready, budget_s, self._timer, self._round)
            self._round += 1
        if self._tcp:  # a TCP listener with a client waiting, and the endpoints with clients
            for ep in {id(d[0]): d[0] for d in keys if isinstance(d, tuple)}.values():
                if not ep.tcp.clients:
                    ep.poll_tcp()
            for ep in self._tcp:
                if ep.tcp.clients:
                    ep.poll_tcp()

    @property
    def counters(self) -> dict:
        out: dict[str, int] = {}
        for ep in self.endpoints:
            for k, v in ep.counters.items():
                out[k] = out.get(k, 0) + v
        return out

    @property
    def datagrams(self) -> dict:
        rej = dict.fromkeys(DATAGRAM_REJECT_REASONS, 0)
        acc = dropped = 0
        for ep in self.endpoints:
            d = ep.datagrams
            acc += d["accepted"]
            dropped += d["kernel_dropped"]
            for r, v in d["rejected"].items():
                rej[r] = rej.get(r, 0) + v
        return {"accepted": acc, "rejected": rej, "kernel_dropped": dropped}

    def close(self) -> None:
        self._sel.close()
        for ep in self.endpoints:
            ep.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
