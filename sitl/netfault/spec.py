"""Fault specifications: a frozen `FaultSpec` (SI units) and its netem-like one-line text.

Grammar (space-separated ``key=value``; netem spellings ``key value ...`` are accepted too)::

    loss=P[,CORR]                       random loss, netem "loss random P CORR"
    gemodel=p[,r[,1-h[,1-k]]]           Gilbert-Elliott loss, netem "loss gemodel ..."
                                        (defaults as tc-netem(8): r = 1-p, 1-h = 100 %, 1-k = 0)
    delay=D[~JITTER[,CORR]]             also netem's "delay D JITTER CORR"
    distribution=uniform|normal|pareto|paretonormal   (default uniform, the kernel's default)
    reorder=P[,CORR]   gap=N            reorder needs a delay; reorder alone means gap=1 and
                                        gap alone means reorder=100 % (as tc / the kernel)
    duplicate=P[,CORR]  corrupt=P[,CORR]
    rate=R                              bit/s; units bit, kbit, mbit, gbit (x1000) and
                                        bps, kbps, mbps, gbps (bytes/s, as tc)
    limit=N                             queue limit in packets (default: no limit)
    partition=T1-T2[,T3-T4...]          simulation seconds; the link is down for T1 <= t < T2
    none  (or the empty string)         no fault

Percentages: ``10%`` or the fraction ``0.1``. Durations: ``100ms``, ``0.1s``, ``2s``,
``250us``, ``5ns``; a bare number is seconds. Every error is a one-line `FaultSpecError`
naming the bad token, e.g. ``fault spec: loss=120%: expected a percentage in [0, 100]``.
`FaultSpec.to_text` writes the canonical text; ``parse_spec(s.to_text()) == s`` for every
valid spec (floats written so that they read back exactly).
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, fields

from filters.params import ParamError, choice, integer, number, optional, param, require, several, validate

__all__ = ["DISTRIBUTIONS", "FaultSpec", "FaultSpecError", "parse_spec"]

DISTRIBUTIONS = ("uniform", "normal", "pareto", "paretonormal")


class FaultSpecError(ValueError):
    """A bad fault specification (one line, names the bad token)."""


def _err(token: str, what: str) -> FaultSpecError:
    return FaultSpecError(f"fault spec: {token}: {what}")


_FRACTION_TEXT = "a fraction in [0, 1]"
_FRACTION = number(0, what=_FRACTION_TEXT)
_FRACTIONS = ("loss", "loss_corr", "delay_corr", "reorder", "reorder_corr", "duplicate", "duplicate_corr",
              "corrupt", "corrupt_corr")


def _partitions(key, value) -> tuple:
    """(t1_s, t2_s) intervals with finite t1 < t2, as a tuple of float pairs (a check (key, value)
    -> value of the filters.params kind)."""
    parts = []
    for iv in value:
        try:
            t1, t2 = (float(x) for x in iv)
        except (TypeError, ValueError):
            raise ParamError(key, f"expected (t1_s, t2_s) intervals, got {iv!r}") from None
        if not (math.isfinite(t1) and math.isfinite(t2)) or not t1 < t2:
            raise ParamError(key, f"expected finite t1 < t2 in every interval, got {iv!r}")
        parts.append((t1, t2))
    return tuple(parts)


@dataclass(frozen=True)
class FaultSpec:
    """What a link does to packets. All fractions in [0, 1], times in s, rate in bit/s.

    ``ge`` is the Gilbert-Elliott model ``(p, r, 1-h, 1-k)`` (None: random loss ``loss``
    with correlation ``loss_corr``). ``rate_bps`` 0 means unlimited; ``limit`` None means no
    queue limit. ``partitions`` are ``(t1_s, t2_s)`` intervals, down for t1 <= t < t2.
    A spec with ``reorder > 0`` has ``gap >= 1`` (gap 0 with reorder is normalised to 1).
    A bad value raises a one-line FaultSpecError (a ValueError) naming the field.
    """

    loss: float = param(0.0, check=_FRACTION, doc="random loss: the fraction of packets dropped")
    loss_corr: float = param(0.0, check=_FRACTION, doc="random loss: its correlation with the previous packet's")
    ge: tuple[float, float, float, float] | None = param(
        None, check=optional(several(_FRACTION, 4)),
        doc="the Gilbert-Elliott loss model (p, r, 1-h, 1-k), fractions; None: random loss (loss, loss_corr)")
    delay_s: float = param(0.0, check=number(0), doc="the delay of every packet, s")
    jitter_s: float = param(0.0, check=number(0), doc="the delay's jitter, s (0: none)")
    delay_corr: float = param(0.0, check=_FRACTION, doc="the jitter's correlation with the previous packet's")
    distribution: str = param("uniform", check=choice(*DISTRIBUTIONS),
                              doc="the jitter's distribution (uniform: the kernel's default)")
    reorder: float = param(0.0, check=_FRACTION,
                           doc="the fraction of packets sent at once, ahead of the delayed ones (needs a delay)")
    reorder_corr: float = param(0.0, check=_FRACTION, doc="reordering: its correlation with the previous packet's")
    gap: int = param(0, check=integer(0), doc="reordering: every gap-th packet is a candidate (0 with reorder: 1)")
    duplicate: float = param(0.0, check=_FRACTION, doc="the fraction of packets sent twice")
    duplicate_corr: float = param(0.0, check=_FRACTION, doc="duplication: its correlation with the previous packet's")
    corrupt: float = param(0.0, check=_FRACTION, doc="the fraction of packets with a flipped bit")
    corrupt_corr: float = param(0.0, check=_FRACTION, doc="corruption: its correlation with the previous packet's")
    rate_bps: float = param(0.0, check=number(0), doc="the link's rate limit, bit/s (0: unlimited)")
    limit: int | None = param(None, check=optional(integer(0)), doc="the queue limit, packets (None: no limit)")
    partitions: tuple[tuple[float, float], ...] = param(
        (), check=_partitions, doc="(t1_s, t2_s) intervals of simulation time in which the link is down (t1 <= t < t2)")

    def __post_init__(self) -> None:
        try:
            validate(self)
            for name in _FRACTIONS:
                require(getattr(self, name) <= 1.0, name, f"expected {_FRACTION_TEXT}, got {getattr(self, name)!r}")
            if self.ge is not None:
                object.__setattr__(self, "ge", tuple(self.ge))
                require(all(x <= 1.0 for x in self.ge), "ge", f"expected 4 fractions in [0, 1] (p, r, 1-h, 1-k), "
                                                              f"got {self.ge!r}")
            require(self.ge is None or not (self.loss > 0 or self.loss_corr > 0), "loss and gemodel",
                    "only one loss model at a time")
            if self.reorder > 0 and self.gap == 0:
                object.__setattr__(self, "gap", 1)
            if self.reorder > 0:
                require(self.has_delay, f"reorder={_fmt_frac(self.reorder)}", "reordering needs a delay (as netem)")
            if self.distribution != "uniform":
                require(self.jitter_s > 0, f"distribution={self.distribution}",
                        "a distribution needs a delay jitter (delay=D~J)")
        except ParamError as exc:
            raise FaultSpecError(f"fault spec: {exc}") from None

    # ------------------------------------------------------------------------------------
    @property
    def is_identity(self) -> bool:
        """True if this spec does nothing to any packet."""
        return self == _IDENTITY

    @property
    def has_delay(self) -> bool:
        return self.delay_s > 0 or self.jitter_s > 0

    def down(self, t_s: float) -> bool:
        """True if the link is partitioned at simulation time t_s."""
        return any(t1 <= t_s < t2 for t1, t2 in self.partitions)

    def to_text(self) -> str:
        """Canonical text; ``parse_spec(self.to_text()) == self``."""
        out: list[str] = []

        def pc(x: float, corr: float = 0.0) -> str:
            s = _fmt_frac(x)
            return s + ("," + _fmt_frac(corr) if corr else "")

        if self.ge is not None:
            out.append("gemodel=" + ",".join(_fmt_frac(x) for x in self.ge))
        elif self.loss or self.loss_corr:
            out.append("loss=" + pc(self.loss, self.loss_corr))
        if self.delay_s or self.jitter_s or self.delay_corr:
            d = "delay=" + _fmt_dur(self.delay_s)
            if self.jitter_s or self.delay_corr:
                d += "~" + _fmt_dur(self.jitter_s)
            if self.delay_corr:
                d += "," + _fmt_frac(self.delay_corr)
            out.append(d)
        if self.distribution != "uniform":
            out.append("distribution=" + self.distribution)
        if self.reorder or self.reorder_corr or self.gap:
            out.append("reorder=" + pc(self.reorder, self.reorder_corr))
        if self.gap and not (self.reorder and self.gap == 1):
            out.append(f"gap={self.gap}")
        if self.duplicate or self.duplicate_corr:
            out.append("duplicate=" + pc(self.duplicate, self.duplicate_corr))
        if self.corrupt or self.corrupt_corr:
            out.append("corrupt=" + pc(self.corrupt, self.corrupt_corr))
        if self.rate_bps:
            out.append("rate=" + _fmt_rate(self.rate_bps))
        if self.limit is not None:
            out.append(f"limit={self.limit}")
        if self.partitions:
            out.append("partition=" + ",".join(f"{_fmt_num(a)}-{_fmt_num(b)}"
                                               for a, b in self.partitions))
        return " ".join(out) if out else "none"

    def __str__(self) -> str:
        return self.to_text()


_IDENTITY = FaultSpec()

# ----------------------------------------------------------------------------------------
# number formats (exact round trip)


def _fmt_num(x: float) -> str:
    r = repr(float(x))
    return r.removesuffix(".0")


def _fmt_frac(x: float) -> str:
    pct = _fmt_num(round(x * 100.0, 12)) + "%"
    try:
        if _parse_frac(pct, "x") == x:
            return pct
    except FaultSpecError:
        pass
    return _fmt_num(x)


def _shortest(x: float, units, parse, fallback: str) -> str:
    """The shortest text ``<number><unit>`` (units: (unit, value of 1 unit)) that ``parse``
    reads back exactly as x."""
    cands = []
    for unit, size in units:
        for v in (round(x / size, 9), x / size):
            s = _fmt_num(v) + unit
            try:
                if parse(s, "x") == x:
                    cands.append(s)
            except FaultSpecError:
                pass
    return min(cands, key=len) if cands else _fmt_num(x) + fallback


def _fmt_dur(x: float) -> str:
    """Shortest of s / ms / us that reads back exactly."""
    return _shortest(x, (("s", 1.0), ("ms", 1e-3), ("us", 1e-6)), _parse_dur, "s")


def _fmt_rate(x: float) -> str:
    """Shortest of bit / kbit / mbit / gbit that reads back exactly."""
    return _shortest(x, (("bit", 1.0), ("kbit", 1e3), ("mbit", 1e6), ("gbit", 1e9)), _parse_rate, "bit")


_NUM = r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?"
_NUM_RE = re.compile(rf"^({_NUM})([a-zA-Z%/]*)$")


def _split_num(s: str, token: str, what: str) -> tuple[float, str]:
    m = _NUM_RE.match(s.strip())
    if not m:
        raise _err(token, f"expected {what}, got {s!r}")
    v = float(m.group(1))
    if not math.isfinite(v):
        raise _err(token, f"expected {what}, got {s!r}")
    return v, m.group(2).lower()


def _parse_frac(s: str, token: str) -> float:
    v, unit = _split_num(s, token, "a percentage (10%) or a fraction (0.1)")
    if unit == "%":
        if not 0.0 <= v <= 100.0:
            raise _err(token, "expected a percentage in [0, 100]")
        return v / 100.0
    if unit:
        raise _err(token, f"unknown unit {unit!r} (expected % or a bare fraction)")
    if not 0.0 <= v <= 1.0:
        raise _err(token, "expected a fraction in [0, 1] (or a percentage: 10%)")
    return v


_DUR_UNITS = {"": 1, "s": 1, "sec": 1, "secs": 1, "ms": 1000, "msec": 1000, "msecs": 1000,
              "us": 1_000_000, "usec": 1_000_000, "usecs": 1_000_000, "ns": 1_000_000_000,
              "nsec": 1_000_000_000}


def _parse_dur(s: str, token: str) -> float:
    v, unit = _split_num(s, token, "a duration (100ms, 0.1s, 250us)")
    if unit not in _DUR_UNITS:
        raise _err(token, f"unknown time unit {unit!r} (s, ms, us, ns)")
    if v < 0:
        raise _err(token, "expected a duration >= 0")
    return v / _DUR_UNITS[unit]


_RATE_UNITS = {"": 1, "bit": 1, "bit/s": 1, "kbit": 1e3, "mbit": 1e6, "gbit": 1e9,
               "bps": 8, "kbps": 8e3, "mbps": 8e6, "gbps": 8e9}


def _parse_rate(s: str, token: str) -> float:
    v, unit = _split_num(s, token, "a rate (1mbit, 64kbit, 9600bit)")
    if unit not in _RATE_UNITS:
        raise _err(token, f"unknown rate unit {unit!r} (bit, kbit, mbit, gbit, bps, kbps, mbps)")
    r = v * _RATE_UNITS[unit]
    if not (math.isfinite(r) and r > 0):
        raise _err(token, "expected a rate > 0")
    return r


def _parse_int(s: str, token: str, lo: int) -> int:
    if not re.fullmatch(r"\+?\d+", s.strip()):
        raise _err(token, f"expected an integer >= {lo}, got {s!r}")
    v = int(s)
    if v < lo:
        raise _err(token, f"expected an integer >= {lo}")
    return v


# ----------------------------------------------------------------------------------------
# parser

_KEYS = ("loss", "gemodel", "delay", "distribution", "reorder", "gap", "duplicate",
         "corrupt", "rate", "limit", "partition")
_ALIASES = {"partitions": "partition", "dup": "duplicate", "drop": "loss", "latency": "delay"}


def _tokens(text: str) -> list[tuple[str, list[str], str]]:
    """Group the text into (key, values, original token text)."""
    groups: list[tuple[str, list[str], str]] = []
    words = text.split()
    i = 0
    while i < len(words):
        w = words[i]
        if "=" in w:
            k, _, v = w.partition("=")
            key = _ALIASES.get(k.lower(), k.lower())
            if key not in _KEYS:
                raise _err(w, f"unknown key {k!r} (expected one of {', '.join(_KEYS)})")
            if v == "":
                raise _err(w, "missing value")
            vals = v.split(",")
            if key == "delay" and "~" in vals[0]:
                d, _, j = vals[0].partition("~")
                vals = [d, j] + vals[1:]
            groups.append((key, vals, w))
            i += 1
            continue
        key = _ALIASES.get(w.lower(), w.lower())
        if key not in _KEYS:
            raise _err(w, f"unknown key (expected key=value with key one of {', '.join(_KEYS)})")
        j = i + 1
        if key == "loss" and j < len(words) and words[j].lower() in ("gemodel", "random", "state"):
            j += 1  # netem's "loss gemodel ..." / "loss random ..."
            if words[j - 1].lower() == "gemodel":
                key = "gemodel"
            elif words[j - 1].lower() == "state":
                raise _err(" ".join(words[i:j + 1]), "the 4-state loss model is not supported "
                                                     "(use gemodel)")
        vals = []
        while j < len(words) and "=" not in words[j] and \
                _ALIASES.get(words[j].lower(), words[j].lower()) not in _KEYS:
            vals.extend(x for x in words[j].split(",") if x != "")
            j += 1
        tok = " ".join(words[i:j])
        if key == "delay" and vals and "~" in vals[0]:
            d, _, jt = vals[0].partition("~")
            vals = [d, jt] + vals[1:]
        if not vals:
            raise _err(tok, "missing value")
        groups.append((key, vals, tok))
        i = j
    return groups


def _nvals(vals: list[str], tok: str, lo: int, hi: int) -> None:
    if not lo <= len(vals) <= hi:
        raise _err(tok, f"expected {lo}{'' if lo == hi else f' to {hi}'} value"
                        f"{'s' if hi > 1 else ''}, got {len(vals)}")


def parse_spec(text: str | FaultSpec | None) -> FaultSpec:
    """Parse the netem-like text (see the module docstring) into a `FaultSpec`.

    A `FaultSpec` is returned as is; None, "" and "none" give the identity spec."""
    if isinstance(text, FaultSpec):
        return text
    if text is None:
        return FaultSpec()
    if not isinstance(text, str):
        raise FaultSpecError(f"fault spec: expected text, got {type(text).__name__}")
    if "\n" in text or "\r" in text:
        raise FaultSpecError("fault spec: must be one line")
    if text.strip().lower() in ("", "none"):
        return FaultSpec()
    kw: dict = {}
    seen: dict[str, str] = {}
    gap_given = False
    for key, vals, tok in _tokens(text):
        if key in seen:
            raise _err(tok, f"{key} given twice (also {seen[key]})")
        seen[key] = tok
        if key in ("loss", "reorder", "duplicate", "corrupt"):
            _nvals(vals, tok, 1, 2)
            kw[key] = _parse_frac(vals[0], tok)
            if len(vals) > 1:
                kw[f"{key}_corr"] = _parse_frac(vals[1], tok)
        elif key == "gemodel":
            _nvals(vals, tok, 1, 4)
            g = [_parse_frac(v, tok) for v in vals]
            p = g[0]
            r = g[1] if len(g) > 1 else 1.0 - p
            one_h = g[2] if len(g) > 2 else 1.0
            one_k = g[3] if len(g) > 3 else 0.0
            kw["ge"] = (p, r, one_h, one_k)
        elif key == "delay":
            _nvals(vals, tok, 1, 3)
            kw["delay_s"] = _parse_dur(vals[0], tok)
            if len(vals) > 1:
                kw["jitter_s"] = _parse_dur(vals[1], tok)
            if len(vals) > 2:
                kw["delay_corr"] = _parse_frac(vals[2], tok)
        elif key == "distribution":
            _nvals(vals, tok, 1, 1)
            d = vals[0].lower()
            if d not in DISTRIBUTIONS:
                raise _err(tok, f"expected one of {', '.join(DISTRIBUTIONS)}")
            kw["distribution"] = d
        elif key == "gap":
            _nvals(vals, tok, 1, 1)
            kw["gap"] = _parse_int(vals[0], tok, 1)
            gap_given = True
        elif key == "rate":
            _nvals(vals, tok, 1, 1)
            kw["rate_bps"] = _parse_rate(vals[0], tok)
        elif key == "limit":
            _nvals(vals, tok, 1, 1)
            kw["limit"] = _parse_int(vals[0], tok, 0)
        elif key == "partition":
            parts = []
            for v in vals:
                m = re.fullmatch(rf"({_NUM})-({_NUM})", v.strip())
                if not m:
                    raise _err(tok, f"expected T1-T2 in seconds, got {v!r}")
                a, b = float(m.group(1)), float(m.group(2))
                if not (math.isfinite(a) and math.isfinite(b) and a < b):
                    raise _err(tok, f"expected finite T1 < T2, got {v!r}")
                parts.append((a, b))
            kw["partitions"] = tuple(parts)
    if gap_given and "reorder" not in kw:
        kw["reorder"] = 1.0  # the kernel: "if gap is set, need to assume 100% probability"
    if "ge" in kw and "loss" in kw:
        raise FaultSpecError(f"fault spec: {seen['gemodel']}: loss and gemodel: only one loss "
                             "model at a time")
    if kw.get("reorder", 0) > 0 and not (kw.get("delay_s", 0) > 0 or kw.get("jitter_s", 0) > 0):
        raise _err(seen["reorder"] if "reorder" in seen else seen["gap"],
                   "reordering needs a delay (as netem)")
    if "distribution" in kw and not kw.get("jitter_s", 0) > 0:
        raise _err(seen["distribution"], "a distribution needs a delay jitter (delay=D~J)")
    return FaultSpec(**kw)


def spec_fields() -> tuple[str, ...]:
    """Names of the FaultSpec fields (for tools that list them)."""
    return tuple(f.name for f in fields(FaultSpec))


# ---------------------------------------------------------------- link names

class LinkNameError(ValueError):
    """A bad link name: ``expected`` says what a link name is; ``show_got``: whether the bad
    value belongs in the message (not when ``expected`` already quotes the forms)."""

    def __init__(self, expected: str, show_got: bool):
        super().__init__(expected)
        self.expected, self.show_got = expected, show_got


def canonical_link(link) -> str:
    """A network-fault link name, checked and normalised: ``mav:<n>[:up|:down]`` (n: the vehicle's
    number in the run, 1..MAX_MAVLINK_FLEET; in MAVLink block 1 it is its system id,
    sitl.mavlink.blocks), ``zenoh:<worker>`` (``gs`` or ``vehicles<k>``) or ``bus:<key
    expression>``. LinkNameError otherwise."""
    from sitl.constants import MAX_MAVLINK_FLEET

    if not isinstance(link, str) or not link:
        raise LinkNameError("a link name", True)
    kind, sep, rest = link.partition(":")
    if kind == "mav" and sep:
        parts = rest.split(":")
        if (1 <= len(parts) <= 2 and parts[0].isdigit() and 1 <= int(parts[0]) <= MAX_MAVLINK_FLEET
                and (len(parts) == 1 or parts[1] in ("up", "down"))):
            return f"mav:{int(parts[0])}" + (f":{parts[1]}" if len(parts) == 2 else "")
        raise LinkNameError(f'expected "mav:SYSID" or "mav:SYSID:up|down" with SYSID the vehicle\'s number in '
                            f"1..{MAX_MAVLINK_FLEET} (its system id in MAVLink block 1)", False)
    if kind == "zenoh" and sep:
        if rest == "gs" or (rest.startswith("vehicles") and rest[8:].isdigit()):
            return link
        raise LinkNameError('expected a worker\'s session "zenoh:gs" or "zenoh:vehicles<k>"', False)
    if kind == "bus" and sep:
        from sitl.bus import KeyExprError, validate_key_expr
        try:
            validate_key_expr(rest)
        except KeyExprError as e:
            raise LinkNameError(f"expected a bus key expression ({e})", False) from None
        return link
    raise LinkNameError('expected a link "mav:SYSID", "zenoh:WORKER" or "bus:KEY/EXPR"', False)
