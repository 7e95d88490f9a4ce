"""The launcher's live status line: aggregates the workers' status lines and the errors."""
from __future__ import annotations

from collections import Counter

from sitl.live.pacer import perf_now


def _rejected_total(status: dict) -> Counter:
    c = Counter()
    for reason, n in (status.get("rejected") or {}).items():
        c[f"bus:{reason}"] += int(n)
    mav = status.get("mavlink") or {}
    rej = mav.get("rejected") if isinstance(mav.get("rejected"), dict) else None
    if rej is not None:
        for reason, n in rej.items():
            if n:
                c[f"mavlink:{reason}"] += int(n)
    else:
        for reason in ("garbage", "bad_crc", "unknown_msgid", "unsigned", "bad_signature", "malformed"):
            if isinstance(mav.get(reason), int) and mav[reason]:
                c[f"mavlink:{reason}"] += mav[reason]
    for k in ("step_errors", "late"):
        if status.get(k):
            c[k] += int(status[k])
    return c


class StatusBoard:
    """Totals over the workers (earlier incarnations of restarted workers included)."""

    def __init__(self):
        self._last_sent = None
        self._last_t = None
        self.msgs_per_s = 0.0

    def snapshot(self, supervisor, scorer, own_bus=None) -> dict:
        sent = 0
        rejected = Counter()
        vehicles = 0
        t_sim = None
        for c in supervisor.children.values():
            for st in c.history + ([c.status] if c.status else []):
                rejected.update(_rejected_total(st))
            for st in c.history:
                sent += int(st.get("sent", 0))
            st = c.status
            if st:
                sent += int(st.get("sent", 0))
                vehicles += int(st.get("vehicles", 0))
                if st.get("t_sim_s") is not None and c.name.startswith("vehicles"):
                    t_sim = st["t_sim_s"] if t_sim is None else min(t_sim, st["t_sim_s"])
        if own_bus is not None:
            for reason, n in own_bus.stats.total.rejected.items():
                rejected[f"launcher-bus:{reason}"] += int(n)
        now = perf_now()
        if self._last_sent is not None and now > self._last_t:
            self.msgs_per_s = max(0.0, (sent - self._last_sent) / (now - self._last_t))
        self._last_sent, self._last_t = sent, now
        errs = {}
        if scorer is not None:
            for (kind, _id), (_t, e) in dict(scorer.latest).items():
                errs[kind] = e
        return {"t_sim_s": t_sim, "vehicles": vehicles, "sent": sent, "msgs_per_s": self.msgs_per_s,
                "rejected": dict(rejected), "rejected_total": sum(rejected.values()), "errors_m": errs,
                "restarts": supervisor.counters.get("restarts", 0), "alive": len(supervisor.alive())}


def format_status(snap: dict, t0_gps_s: float, duration_s: float) -> str:
    t = snap["t_sim_s"]
    ts = "   --  " if t is None else f"{t - t0_gps_s:7.1f}"
    e = snap["errors_m"]
    be = f"{e['beacon']:8.1f} m" if "beacon" in e else "     -- m"
    se = f"{e['sonde']:7.1f} m" if "sonde" in e else "    -- m"
    return (f"t {ts}/{duration_s:.0f} s | vehicles {snap['vehicles']:4d} | {snap['msgs_per_s']:7.0f} msg/s | "
            f"rejected {snap['rejected_total']:5d} | beacon err {be} | sonde err {se} | "
            f"workers {snap['alive']} restarts {snap['restarts']}")
