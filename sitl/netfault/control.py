"""Run-time control of the network faults of a live run.

The control key ``<run>/ctl/fault`` carries a `sitl.bus.schema.FaultControl` (``link``,
``spec``). The launcher holds a `FaultBoard`: every link of the run (``mav:<sysid>``, its
``:up`` / ``:down`` halves, ``zenoh:<worker>``, ``bus:<key expression>``) with what applies it
(a proxy's or a publisher filter's ``set``) and the history of the specs applied. It answers
every request on ``<run>/ctl/fault/ack`` with a FaultControl whose ``seq`` is the request's
and whose ``spec`` is the applied spec's canonical text, or ``error: <one line>`` (an unknown
link, a bad spec: counted in ``bad``, the run goes on). A request whose link is ``?`` asks for
the list: the answer's ``spec`` is a JSON object link -> current spec text.

Bus-key links (``bus:...``) are applied by the publishing workers themselves
(`WorkerFaultControl`, each worker's fault filter); the launcher validates, records and
acknowledges them.

Times: simulated seconds since the run's start (what a spec's ``partition=T1-T2`` means).
"""
from __future__ import annotations

import json
import threading
from collections import Counter
from collections.abc import Callable
from dataclasses import asdict, is_dataclass
from typing import Any

# the control keys and the request loop are the bus's (light: a run without faults does not load
# this package); the board below answers them in a run with faults
from sitl.bus.faultctl import (  # noqa: F401
    ACK_SUFFIX,
    CTL_SUFFIX,
    ERROR_PREFIX,
    LIST_LINK,
    ack_key,
    control_key,
    serve,
)


def canonical_link(link: str) -> str:
    """A link name checked and normalised as the scenario's [faults] keys (ValueError, one line)."""
    from sitl.netfault.spec import LinkNameError
    from sitl.netfault.spec import canonical_link as check

    try:
        return check(link)
    except LinkNameError as e:
        if not e.show_got:
            raise ValueError(f"link {link!r}: {e.expected}") from None
        g = repr(link)
        raise ValueError(f"link {link!r}: expected {e.expected}, got {g if len(g) <= 60 else g[:57] + '...'}") from None


def spec_text(spec) -> str:
    t = spec.to_text()
    return t if t else "none"


def truth_dict(truth) -> dict:
    """A LinkTruth (dataclass or object with counters) as a plain JSON-able dict."""
    if truth is None:
        return {}
    if callable(getattr(truth, "counters", None)):  # LinkTruth
        truth = truth.counters()
    if isinstance(truth, dict):
        src = truth
    elif is_dataclass(truth):
        src = asdict(truth)
    else:
        src = {k: v for k, v in vars(truth).items() if not k.startswith("_")}
    out = {}
    for k, v in src.items():
        if isinstance(v, (bool, int, float, str)) or v is None:
            out[k] = v
        elif isinstance(v, dict):
            out[k] = {str(a): b for a, b in v.items() if isinstance(b, (bool, int, float, str))}
        elif hasattr(v, "item"):  # numpy scalar
            out[k] = v.item()
    return out


def add_truths(a: dict, b: dict) -> dict:
    """Sum two truth dicts (counts add, ``*_max`` takes the max, nested dicts add)."""
    out = dict(a)
    for k, v in b.items():
        if isinstance(v, dict):
            out[k] = add_truths(out.get(k, {}), v)
        elif isinstance(v, bool) or not isinstance(v, (int, float)):
            out[k] = v
        elif k.endswith("_max"):
            out[k] = max(out.get(k, v), v)
        else:
            out[k] = out.get(k, 0) + v
    return out


class _Link:
    __slots__ = ("apply", "current", "history", "name", "truth")

    def __init__(self, name, apply, truth):
        self.name = name
        self.apply = apply  # apply(FaultSpec, t_s)
        self.truth = truth  # () -> dict, or None
        self.history: list[dict] = []
        self.current = "none"


class FaultBoard:
    """The links of a live run and the faults applied to them (module text).

    ``clock()``: simulated seconds since the run's start (0 before it starts)."""

    def __init__(self, clock: Callable[[], float] = lambda: 0.0, bus_keys: list[str] | None = None):
        self.clock = clock
        self.bus_keys = bus_keys  # the keys the run publishes: a bus rule must match one (None: not checked)
        self.links: dict[str, _Link] = {}
        self.bus_rules: dict[str, _Link] = {}  # "bus:<expr>" -> its record (applied by the workers)
        self.bus_order: list[str] = []  # the rules in KeyFaults' order (a rule added at run time goes first)
        self.bad: Counter = Counter()
        self.requests = 0
        self.errors: list[str] = []  # the last few error lines
        self.on_change: Callable[[], None] | None = None  # called after each change made by a request
        self._lock = threading.RLock()

    def add_link(self, name: str, apply: Callable[[Any, float], None],
                 truth: Callable[[], dict] | None = None) -> None:
        self.links[name] = _Link(name, apply, truth)

    def _record(self, rec: _Link, spec, t_s: float, by: str) -> None:
        text = spec_text(spec)
        rec.current = text
        # a change before the run's start (the clock is far below 0 then) holds from the start: 0
        rec.history.append({"t_s": round(max(float(t_s), 0.0), 6), "spec": text, "by": by})

    def set(self, link: str, text: str, *, by: str = "control") -> str:
        """Apply ``text`` to ``link`` now; returns the canonical spec text. ValueError (one line)
        for an unknown link or a bad spec; nothing is changed then."""
        from sitl.netfault import FaultSpecError, parse_spec
        with self._lock:
            name = canonical_link(link)
            try:
                spec = parse_spec(text)
            except FaultSpecError as e:
                raise ValueError(" ".join(str(e).split())) from None
            t = float(self.clock())
            if name.startswith("bus:"):
                if self.bus_keys is not None and name not in self.bus_rules:
                    from sitl.bus.transport import key_matches
                    if not any(key_matches(name[4:], k) for k in self.bus_keys):
                        sample = ", ".join([k for k in self.bus_keys if "/truth/" not in k][:5])
                        raise ValueError(f"bus rule {link!r} matches no key this run publishes "
                                         f"(they look like {sample})")
                rec = self.bus_rules.get(name)
                if rec is None:
                    rec = self.bus_rules[name] = _Link(name, None, None)
                    if by == "scenario":
                        self.bus_order.append(name)
                    else:  # as KeyFaults.set: a new rule goes ahead of the others
                        self.bus_order.insert(0, name)
                self._record(rec, spec, t, by)
                return rec.current
            targets = [name]
            if name.startswith("mav:") and name.count(":") == 1 and name not in self.links:
                targets = [f"{name}:up", f"{name}:down"]
            if not all(n in self.links for n in targets):
                known = ", ".join(sorted(self.links)) or "none"
                raise ValueError(f"unknown link {link!r} in this run (links: {known})")
            for n in targets:
                self.links[n].apply(spec, t)
                self._record(self.links[n], spec, t, by)
            return spec_text(spec)

    def handle(self, msg) -> tuple[bool, str]:
        """A FaultControl request: (ok, canonical spec or the error line). Never raises."""
        with self._lock:
            self.requests += 1
            if msg.link == LIST_LINK:
                return True, json.dumps(self.current(), separators=(",", ":"))
            try:
                text = self.set(msg.link, msg.spec)
                if self.on_change is not None:
                    try:
                        self.on_change()
                    except Exception:
                        pass
                return True, text
            except ValueError as e:
                reason = "unknown link" if "unknown link" in str(e) or str(e).startswith("link ") else "bad spec"
                self.bad[reason] += 1
                line = " ".join(str(e).split())
                self.errors = (self.errors + [line])[-20:]
                return False, line
            except Exception as e:  # an applier failed: counted, the run goes on
                self.bad["apply failed"] += 1
                line = f"{msg.link}: applying failed: {type(e).__name__}: {e}"
                self.errors = (self.errors + [line])[-20:]
                return False, " ".join(line.split())

    def current(self) -> dict:
        out = {n: rec.current for n, rec in self.links.items()}
        out.update({n: rec.current for n, rec in self.bus_rules.items()})
        return out

    def report(self, bus_truths: dict | None = None) -> dict:
        """The report's ``faults`` block: per link the specs applied over time and the truth
        counters (proxies: here; bus keys: ``bus_truths`` {link: truth dict} from the workers)."""
        links = {}
        for n, rec in list(self.links.items()) + list(self.bus_rules.items()):
            d = {"current": rec.current, "history": rec.history}
            if rec.truth is not None:
                try:
                    d["truth"] = rec.truth()
                except Exception as e:
                    d["truth_error"] = f"{type(e).__name__}: {e}"
            if bus_truths and n in bus_truths:
                d["truth"] = bus_truths[n]
            links[n] = d
        for n, t in (bus_truths or {}).items():  # a rule only the workers know (none set)
            links.setdefault(n, {"current": None, "history": [], "truth": t})
        return {"links": links, "requests": self.requests, "bad_requests": dict(self.bad),
                "errors": self.errors}


class WorkerFaultControl:
    """A worker's side: its bus-key fault filter (a `sitl.netfault.KeyFaults`) changed by the
    ``bus:`` requests on the control key (the launcher validates and answers them)."""

    def __init__(self, bus, run_id: str, key_faults):
        self.bus = bus
        self.run_id = run_id
        self.kf = key_faults
        self.applied = 0
        self.bad: Counter = Counter()
        self._seen: dict = {}  # (source_id, seq) of requests applied (the CLI repeats one until answered)

    def on_control(self, key: str, msg) -> None:
        from sitl.netfault import FaultSpecError, parse_spec
        link = getattr(msg, "link", "")
        if key != control_key(self.run_id) or not link.startswith("bus:"):
            return
        rid = (msg.source_id, msg.seq)
        if rid in self._seen:
            return
        self._seen[rid] = True
        if len(self._seen) > 256:
            del self._seen[next(iter(self._seen))]
        expr = link[4:]
        try:
            from sitl.bus import KeyExprError, validate_key_expr
            validate_key_expr(expr)
            spec = parse_spec(msg.spec)
        except (FaultSpecError, KeyExprError) as e:
            self.bad[type(e).__name__] += 1
            return
        self.bus.with_faults(lambda: self.kf.set(expr, spec, self.bus.fault_now_s))
        self.applied += 1

    def truths(self) -> dict:
        """{"bus:<rule>": summed truth dict over the keys the rule takes now} (first match wins;
        a key whose rule changed at run time is counted under its current rule)."""
        from sitl.bus import key_matches
        out: dict[str, dict] = {}
        try:
            per_key, rules = self.bus.with_faults(lambda: ({k: truth_dict(t) for k, t in self.kf.truths().items()},
                                                           [e for e, _ in self.kf.rules]))
        except Exception:
            return out
        for key, truth in per_key.items():
            rule = next((r for r in rules if key_matches(r, key)), None)
            if rule is None:
                continue
            name = f"bus:{rule}"
            out[name] = add_truths(out.get(name, {}), truth)
        return out


__all__ = ["ACK_SUFFIX", "CTL_SUFFIX", "ERROR_PREFIX", "LIST_LINK", "FaultBoard", "WorkerFaultControl",
           "ack_key", "add_truths", "canonical_link", "control_key", "serve", "spec_text", "truth_dict"]
