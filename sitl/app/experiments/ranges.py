"""Bounded-number checks for the experiments' scenario declarations (sitl.params).

The core's number() has a lower bound only; a scenario field such as an elevation mask in
[5, 90) or a probability in [0, 1] needs both. ``within`` is that check, made of number() so
that its messages read the same: ``key: expected a number in [5, 90), got 95.0``. Kept here
(the experiments' own layer) rather than in filters/params.py, which these modules do not own;
it is a candidate for number(..., hi=...) there.
"""
from __future__ import annotations

from sitl.params import Check, ParamError, number

__all__ = ["within"]


def within(lo: float, hi: float, *, lo_open: bool = False, hi_open: bool = False, what: str | None = None) -> Check:
    """A finite float in [lo, hi] ((lo, ...) if lo_open, (..., hi) if hi_open); an int is taken as one."""
    if what is None:
        what = f"a number in {'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
    base = number(lo, lo_open=lo_open, what=what)

    def upper(x: float, shown) -> float:
        if x > hi or (hi_open and x == hi):
            raise ParamError("", f"expected {what}, got {shown}")
        return x

    return Check(lambda v: upper(base("", v), repr(v)), lambda text: upper(base.parse(text), text))
