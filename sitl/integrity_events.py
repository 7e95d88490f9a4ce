"""Integrity events: a monitor epoch's Report -> bus `IntegrityEvent` messages.

Shared by the UAV onboard navigation (vehicles/) and the ground-station trackers
(ground_station/): both import it from here (sitl imports neither of them).

One event per channel and epoch at most, from the `filters.integrity.Report` of that epoch:

=============  ==========================================================  ================
``event``      when                                                        ``statistic``
=============  ==========================================================  ================
``step``       the channel is newly excluded with a jump this epoch        its row's beta
               (jumps on ``persist`` consecutive epochs: a step that        of largest |.|
               stays; a window test may have fired as well)
``ramp``       the channel is newly excluded by a window test alone        the window
                                                                           statistic that
                                                                           tripped (bias
                                                                           test if above
                                                                           its tolerance,
                                                                           else mean beta^2)
``outlier``    a row of a channel that is not (now) excluded failed the    its beta
               jump test: that row is left out of this epoch's update
``readmit``    an excluded channel comes back                              NaN
=============  ==========================================================  ================

An excluded channel's own jumps are not repeated as events (its exclusion said it); with
``isolate=False`` (detect only) nothing is excluded, so every faulty epoch is an event.

Channel names are bus tokens (``[A-Za-z0-9_.-]``, 1..64 chars), e.g. ``uav3.G12`` (a UAV's
satellite), ``s0001.relay.G07`` (a relayed satellite of sonde s0001), ``s0001.arls1.az``
(a radar axis). The event's time is the epoch's GPS time.
"""
from __future__ import annotations

import math
from collections import Counter

import numpy as np

from sitl.bus.schema import IntegrityEvent, check_id, key_for

__all__ = ["EVENT_KINDS", "IntegrityEventPublisher", "channel_events", "events_from_report"]

EVENT_KINDS = ("step", "ramp", "outlier", "readmit")


def channel_events(report, channels, bias_threshold: float = math.inf):
    """The epoch's events as (batch index tuple, channel, kind, statistic), in batch then
    channel order.

    report: a filters.integrity.Report (batch..., m rows / C channels); channels (m,) ints,
    the row -> channel map given to the monitor; bias_threshold: the monitor's bias-test
    tolerance (IntegrityConfig.bias_threshold()), to name which window statistic tripped.
    """
    ch = np.asarray(channels)
    beta = np.asarray(report.beta, dtype=float)
    m = beta.shape[-1]
    C = np.asarray(report.excluded).shape[-1]
    if ch.shape != (m,) or (m and (ch.min() < 0 or ch.max() >= C)):
        raise ValueError(f"channels must be ({m},) ints in [0, {C}), got shape {ch.shape}")
    onehot = ch[:, None] == np.arange(C)[None, :]  # (m, C)
    jump = np.asarray(report.jump, dtype=bool)
    drift = np.asarray(report.drift, dtype=bool)
    jump_ch = (jump[..., :, None] & onehot).any(axis=-2)
    newly = np.asarray(report.newly_excluded, dtype=bool)
    excl = np.asarray(report.excluded, dtype=bool)
    readmit = np.asarray(report.readmitted, dtype=bool)
    step = newly & jump_ch  # excluded with a jump this epoch: the persistence rule (a window test may fire too)
    ramp = newly & ~jump_ch  # excluded by a window test alone: a drift
    outlier = jump_ch & ~newly & ~excl
    any_ev = step | ramp | outlier | readmit
    if not any_ev.any():
        return []
    out = []
    for idx in zip(*np.nonzero(any_ev)):
        b, c = tuple(int(i) for i in idx[:-1]), int(idx[-1])
        rows = np.flatnonzero(ch == c)
        if readmit[idx]:
            out.append((b, c, "readmit", math.nan))
            continue
        if ramp[idx]:
            bias = np.asarray(report.bias_stat, dtype=float)[b][rows]
            ms = np.asarray(report.drift_stat, dtype=float)[b][rows]
            d = drift[b][rows]
            if np.any(d & (bias > bias_threshold)):
                stat = float(np.max(np.where(d, bias, -np.inf)))
            else:
                stat = float(np.max(np.where(d, ms, -np.inf)))
            out.append((b, c, "ramp", stat))
            continue
        br = beta[b][rows]
        stat = float(br[np.argmax(np.abs(br))])
        out.append((b, c, "step" if step[idx] else "outlier", stat))
    return out


def events_from_report(report, channels, t_gps_s: float, names, *, source_id: str, seq: int = 0,
                       bias_threshold: float = math.inf) -> list[IntegrityEvent]:
    """The epoch's IntegrityEvent messages, numbered seq, seq + 1, ...

    names: the channel name of (batch index tuple, channel) -- a callable, or an array of
    str (batch..., C) / (C,) indexed by it."""
    evs = channel_events(report, channels, bias_threshold)
    out = []
    for i, (b, c, kind, stat) in enumerate(evs):
        name = names(b, c) if callable(names) else _lookup(names, b, c)
        out.append(IntegrityEvent(t_gps_s=float(t_gps_s), source_id=source_id, seq=seq + i, channel=name,
                                  event=kind, statistic=stat))
    return out


def _lookup(names, b, c):
    a = np.asarray(names)
    return str(a[b + (c,)] if a.ndim > 1 else a[c])


class IntegrityEventPublisher:
    """Turns monitor Reports into IntegrityEvents, numbers them per source and publishes them
    on ``<run_id>/gs/integrity/<channel>`` through ``transport`` (anything with
    ``publish(key, msg)``, e.g. sitl.bus.InMemoryTransport; None: only returned).

    run_id, source_id: a str, or a callable of the batch index tuple (e.g. one run id per
    Monte Carlo trial, one source per UAV); each source numbers its events from 0.
    ``counts`` (Counter): events by kind; ``published``: how many went out."""

    def __init__(self, run_id, source_id, transport=None, bias_threshold: float = math.inf):
        self.run_id = run_id if callable(run_id) else check_id(run_id, "run_id")
        self.source_id = source_id if callable(source_id) else check_id(source_id, "source_id")
        self.transport = transport
        self.bias_threshold = float(bias_threshold)
        self.seq: dict = {}
        self.counts: Counter = Counter()
        self.published = 0

    def __call__(self, report, channels, t_gps_s: float, names, config=None) -> list[IntegrityEvent]:
        """The epoch's events (published); config: the monitor's IntegrityConfig (its bias-test
        tolerance names the window statistic of a ramp event; default: the constructor's)."""
        thr = self.bias_threshold if config is None else config.bias_threshold()
        out = []
        for b, c, kind, stat in channel_events(report, channels, thr):
            src = self.source_id(b) if callable(self.source_id) else self.source_id
            seq = self.seq.get(src, 0)
            self.seq[src] = seq + 1
            name = names(b, c) if callable(names) else _lookup(names, b, c)
            e = IntegrityEvent(t_gps_s=float(t_gps_s), source_id=src, seq=seq, channel=name, event=kind,
                               statistic=stat)
            self.counts[kind] += 1
            out.append(e)
            if self.transport is not None:
                run = self.run_id(b) if callable(self.run_id) else self.run_id
                self.transport.publish(key_for(run, e), e)
                self.published += 1
        return out
