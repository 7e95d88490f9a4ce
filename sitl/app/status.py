"""The launcher's live status line: aggregates the workers' status lines and the errors."""
from __future__ import annotations

from collections import Counter

from sitl.pacing import perf_now


def _rejected_total(status: dict) -> Counter:
    """A worker's rejected inputs that only it can see: its time guard's refusals (the ground
    station's ``time:future`` / ``time:stale``), its MAVLink datagrams, its failed steps and
    late inputs. Bus payloads are counted once for the whole run by the launcher's audit
    (`sitl.bus.audit.PayloadAudit`, every key), not here: each worker decodes only the keys it
    subscribes to, and the same bad payload would count once per receiver."""
    c = Counter()
    for reason, n in (status.get("rejected") or {}).items():
        if reason.startswith("time:"):
            c[reason] += int(n)
    mav = status.get("mavlink") or {}
    rej = mav.get("rejected") if isinstance(mav.get("rejected"), dict) else None
    if rej is not None:
        for reason, n in rej.items():
            if n:
                c[f"mavlink:{reason}"] += int(n)
    dropped = (mav.get("datagrams") or {}).get("kernel_dropped") if isinstance(mav.get("datagrams"), dict) else None
    if dropped:  # datagrams the kernel dropped before the endpoint read them (SO_RXQ_OVFL)
        c["mavlink:kernel_dropped"] += int(dropped)
    for k in ("step_errors", "late"):
        if status.get(k):
            c[k] += int(status[k])
    return c


def run_rejected(supervisor, audit) -> Counter:
    """The run's rejected inputs: every bus payload the audit refused (``bus:<reason>``, once
    each) and what the workers alone see (`_rejected_total`), earlier incarnations included."""
    rejected = Counter()
    if audit is not None:
        for reason, n in audit.rejected_by_reason().items():
            rejected[f"bus:{reason}"] += int(n)
    for c in supervisor.children.values():
        for st in c.history + ([c.status] if c.status and c.status not in c.history else []):
            rejected.update(_rejected_total(st))
    return rejected


class StatusBoard:
    """Totals over the workers (earlier incarnations of restarted workers included)."""

    def __init__(self):
        self._last_sent = None
        self._last_t = None
        self.msgs_per_s = 0.0

    def snapshot(self, supervisor, scorer, audit=None, now_sim_s: float | None = None) -> dict:
        """now_sim_s: the launcher's simulation clock (the age of the latest estimates)."""
        sent = 0
        vehicles = 0
        t_sim = None
        for c in supervisor.children.values():
            for st in c.history:
                sent += int(st.get("sent", 0))
            st = c.status
            if st:
                sent += int(st.get("sent", 0))
                vehicles += int(st.get("vehicles", 0))
                if st.get("t_sim_s") is not None and c.name.startswith("vehicles"):
                    t_sim = st["t_sim_s"] if t_sim is None else min(t_sim, st["t_sim_s"])
        rejected = run_rejected(supervisor, audit)
        now = perf_now()
        if self._last_sent is not None and now > self._last_t:
            self.msgs_per_s = max(0.0, (sent - self._last_sent) / (now - self._last_t))
        self._last_sent, self._last_t = sent, now
        errs, ages = {}, {}
        if scorer is not None:
            for (kind, _id), (_t, e) in dict(scorer.latest).items():
                errs[kind] = e
            if now_sim_s is not None:
                for (kind, _id), t_est in dict(scorer.last_estimate_t).items():
                    ages[kind] = max(0.0, now_sim_s - t_est)
        return {"t_sim_s": t_sim, "vehicles": vehicles, "sent": sent, "msgs_per_s": self.msgs_per_s,
                "rejected": dict(rejected), "rejected_total": sum(rejected.values()), "errors_m": errs,
                "estimate_age_s": ages, "restarts": supervisor.counters.get("restarts", 0),
                "alive": len(supervisor.alive())}


def _err_text(kind: str, snap: dict, stale_after_s: float | None, width: int) -> str:
    """``12.3 m`` (the latest scored error), with the age of the latest estimate when it is older
    than two seconds, and ``STALE`` once older than stale_after_s (no estimate for that long: the
    error shown is that old)."""
    e = snap["errors_m"].get(kind)
    age = (snap.get("estimate_age_s") or {}).get(kind)
    text = f"{e:{width}.1f} m" if e is not None else " " * (width - 2) + "-- m"
    if age is not None and stale_after_s is not None and age > stale_after_s:
        return text + f" STALE {age:.0f} s"
    if age is not None and age >= 2.0:
        return text + f" ({age:.0f} s old)"
    return text


def format_status(snap: dict, t0_gps_s: float, duration_s: float, stale_after_s: float | None = None) -> str:
    t = snap["t_sim_s"]
    ts = "   --  " if t is None else f"{t - t0_gps_s:7.1f}"
    be = _err_text("beacon", snap, stale_after_s, 8)
    se = _err_text("sonde", snap, stale_after_s, 7)
    return (f"t {ts}/{duration_s:.0f} s | vehicles {snap['vehicles']:4d} | {snap['msgs_per_s']:7.0f} msg/s | "
            f"rejected {snap['rejected_total']:5d} | beacon err {be} | sonde err {se} | "
            f"workers {snap['alive']} restarts {snap['restarts']}")
