"""Parameters declared once: the declaration core every layer uses.

A configuration is a frozen dataclass whose fields are declared with ``param(default, check=...,
doc=...)``: the field carries its default, its check and its one-paragraph documentation, and
``validate(self)`` in ``__post_init__`` runs every check, storing what it returns (a float for a
number, a float array for an array). A bad value raises ``ParamError`` (a ValueError) with one
line, ``key: expected ..., got ...``. A rule that relates two fields is written after
``validate(self)`` with ``require(condition, key, reason)``.

    @dataclass(frozen=True)
    class Receiver:
        sigma_pr_m: float = param(3.0, check=number(0, lo_open=True), doc="pseudorange noise (1 sigma), m")
        def __post_init__(self):
            validate(self)

This module is plain Python (no numpy beyond the array checks, no I/O): it sits in filters/, the
lowest layer, so that filters, the world (sitl), the components and the composition root declare
parameters the same way. sitl.params adds what only the composition root needs from the same
declaration: the TOML form of a section and the command-line flags with their --help texts.
"""
from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import MISSING

import numpy as np

__all__ = ["param", "checks", "docs", "ParamError", "Check", "integer", "number", "choice", "switch", "string",
           "optional", "several", "from_text", "array", "vec3", "reworded", "default_of", "flag_of", "validate",
           "require", "instance_of", "as_given"]


def param(default=MISSING, *, check, doc: str, default_factory=MISSING, kw_only=MISSING, flag=None, metavar=None,
          cli=True, shown=None, note="", default_help=None):
    """A dataclass field with its check (key, value) -> value and its one-paragraph doc.

    For an option on the command line (add_flags): ``flag`` (default --name-with-dashes),
    ``metavar``, ``cli=False`` to keep it off the command line; the --help text is the doc then
    "(default X<note>)", X the default or ``shown`` (a text or a callable giving the value that
    stands for a None default, e.g. another dataclass's declared default), or ``default_help``
    instead of that parenthesis. ``kw_only`` as dataclasses.field's (a field without a default
    after fields with one)."""
    if not doc or not callable(check):
        raise TypeError("param: a check and a doc are required")
    md = {"check": check, "doc": " ".join(doc.split())}
    extra = {"flag": flag, "metavar": metavar, "shown": shown, "default_help": default_help}
    md.update({k: v for k, v in extra.items() if v is not None})
    if note:
        md["note"] = note
    if not cli:
        md["cli"] = False
    return dataclasses.field(default=default, default_factory=default_factory, kw_only=kw_only, metadata=md)


@functools.lru_cache(maxsize=None)
def _declared(cls) -> tuple:
    """The declared fields of ``cls`` (cached: validate runs in the __post_init__ of models
    built at every step)."""
    return tuple(f for f in dataclasses.fields(cls) if "check" in f.metadata)


def checks(cls) -> dict:
    """{field name: check} of the declared parameters of dataclass ``cls``, in declaration order."""
    return {f.name: f.metadata["check"] for f in _declared(cls)}


def docs(cls) -> dict:
    """{field name: doc} of the declared parameters of dataclass ``cls``."""
    return {f.name: f.metadata["doc"] for f in _declared(cls)}


class ParamError(ValueError):
    """A parameter with a bad value: ``key: reason`` (one line); ``reason`` alone for a flag."""

    def __init__(self, key: str, reason: str):
        self.key, self.reason = key, reason
        super().__init__(f"{key}: {reason}" if key else reason)


class Check:
    """check(key, value) -> value or ParamError(key, ...); parse(text) -> value or ParamError('', ...)."""

    def __init__(self, test, parse=None, *, cli=None, show=None):
        self._test, self._parse = test, parse
        self.cli = dict(cli or {})  # argparse keywords of the flag besides type (choices, action, nargs)
        self.show = show or _show  # a default as the help text shows it

    def __call__(self, key: str, value):
        try:
            return self._test(value)
        except ParamError as exc:
            raise ParamError(key, exc.reason) from None

    def parse(self, text: str):
        return self._parse(text) if self._parse is not None else self._test(text)


def _show(v) -> str:
    if isinstance(v, float):
        return f"{v:g}"
    if isinstance(v, (tuple, list)):
        return " ".join(_show(x) for x in v)
    return str(v)


def integer(lo: int | None = None, hi: int | None = None, what: str | None = None, *, numpy: bool = False) -> Check:
    """An integer (not a bool) in [lo, hi]; from text, int(text). numpy=True: a numpy integer
    too (stored as an int)."""
    if what is None:
        what = {1: "a positive integer", 0: "an integer >= 0"}.get(lo, "an integer") if hi is None else \
            f"an integer in {lo}..{hi}"
        if lo not in (None, 0, 1) and hi is None:
            what = f"an integer >= {lo}"

    kinds = (int, np.integer) if numpy else int

    def test(v):
        if isinstance(v, bool) or not isinstance(v, kinds):
            raise ParamError("", f"expected {what}, got {v!r}")
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            raise ParamError("", f"expected {what}, got {v}")
        return int(v) if numpy else v

    def parse(text):
        try:
            v = int(text)
        except ValueError:
            raise ParamError("", f"expected {what}, got {text!r}") from None
        return test(v)

    return Check(test, parse)


def number(lo: float | None = None, *, lo_open: bool = False, hi: float | None = None, hi_open: bool = False,
           finite: bool = True, what: str | None = None, numpy: bool = False) -> Check:
    """A float (an int is taken as one), finite unless finite=False, >= lo (> lo if lo_open) and
    <= hi (< hi if hi_open); from text, float(text). numpy=True: a numpy integer or float too."""
    if what is None:
        if hi is not None:
            what = (f"a number in {'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}" if lo is not None
                    else ("a finite number" if finite else "a number") + f" {'<' if hi_open else '<='} {hi:g}")
        else:
            what = "a positive finite number" if (lo == 0 and lo_open) else \
                ("a finite number" if finite else "a number") + ("" if lo is None else f" {'>' if lo_open else '>='} {lo:g}")
    loose = what.replace("positive finite", "positive").replace("finite ", "")  # a word that is no number
    kinds = (int, float, np.integer, np.floating) if numpy else (int, float)

    def ok(x):
        return not ((finite and not math.isfinite(x)) or x != x or
                    (lo is not None and (x <= lo if lo_open else x < lo)) or
                    (hi is not None and (x >= hi if hi_open else x > hi)))

    def test(v):
        if isinstance(v, bool) or not isinstance(v, kinds):
            raise ParamError("", f"expected {what}, got {v!r}")
        if not ok(float(v)):
            raise ParamError("", f"expected {what}, got {v!r}")
        return float(v)

    def parse(text):
        try:
            v = float(text)
        except ValueError:
            raise ParamError("", f"expected {loose}, got {text!r}") from None
        if not ok(v):
            raise ParamError("", f"expected {what}, got {text}")
        return v

    return Check(test, parse)


def choice(*options: str) -> Check:
    """One of the strings ``options`` (argparse's choices on the command line)."""
    def test(v):
        if v not in options:
            raise ParamError("", f"expected one of {', '.join(options)}, got {v!r}")
        return v

    return Check(test, cli={"choices": options})


def switch(*, numpy: bool = False) -> Check:
    """A boolean: a flag that sets it (store_true; the default is False). numpy=True: a numpy
    bool too (stored as a bool)."""
    kinds = (bool, np.bool_) if numpy else bool

    def test(v):
        if not isinstance(v, kinds):
            raise ParamError("", f"expected true or false, got {v!r}")
        return bool(v)

    return Check(test, cli={"action": "store_true"})


def string() -> Check:
    """Any string."""
    def test(v):
        if not isinstance(v, str):
            raise ParamError("", f"expected a string, got {v!r}")
        return v

    return Check(test)


def instance_of(cls: type, *, none: bool = False, what: str | None = None) -> Check:
    """An instance of ``cls`` (or None if ``none``), stored as it is: a nested settings object.
    ``what`` words the message as given (default: the class's module and name, "or None")."""
    if what is None:
        what = f"a {cls.__module__}.{cls.__name__}" + (" or None" if none else "")

    def test(v):
        if not (isinstance(v, cls) or (none and v is None)):
            raise ParamError("", f"expected {what}, got {_brief(v)}")
        return v

    return Check(test)


def as_given(check: Check) -> Check:
    """``check``'s test, the value stored as given (a tuple stays a tuple, so a frozen
    settings object stays hashable and comparable field by field)."""
    def test(v):
        check("", v)
        return v

    return Check(test)


def optional(check: Check) -> Check:
    """None (the parameter is not given) or what ``check`` takes."""
    return Check(lambda v: None if v is None else check("", v), check.parse, cli=check.cli, show=check.show)


def several(check: Check, nargs) -> Check:
    """A list of values each of which ``check`` takes: nargs=2 (a pair) or "+" (one or more) words."""
    def test(v):
        if not isinstance(v, (list, tuple)) or (isinstance(nargs, int) and len(v) != nargs) or not v:
            raise ParamError("", f"expected {nargs} values, got {v!r}")
        return [check("", x) for x in v]

    return Check(test, check.parse, cli={**check.cli, "nargs": nargs}, show=check.show)


def from_text(parse, show=None) -> Check:
    """A check made of a text parser (an argparse type: text -> value, ArgumentTypeError): a string
    value is parsed; any other value is taken as it is (a default, a value a caller built)."""
    def test(v):
        if isinstance(v, str):
            try:
                return parse(v)
            except (ValueError, TypeError) as exc:  # argparse.ArgumentTypeError is an Exception
                raise ParamError("", str(exc)) from None
            except Exception as exc:
                if type(exc).__name__ == "ArgumentTypeError":
                    raise ParamError("", str(exc)) from None
                raise
        return v

    return Check(test, parse, show=show)


def default_of(cls, name: str):
    """The declared default of field ``name`` of dataclass ``cls`` (to use it elsewhere without
    writing it again)."""
    f = next((f for f in dataclasses.fields(cls) if f.name == name), None)
    if f is None:
        raise AttributeError(f"{cls.__name__} has no field {name!r}")
    if f.default is not MISSING:
        return f.default
    if f.default_factory is not MISSING:
        return f.default_factory()
    raise AttributeError(f"{cls.__name__}.{name} has no default")


def flag_of(cls, name: str) -> str:
    """The command-line flag of option ``name`` of ``cls``."""
    f = next(f for f in dataclasses.fields(cls) if f.name == name)
    return f.metadata.get("flag") or "--" + name.replace("_", "-")


def validate(obj, flags: bool = False) -> None:
    """Run the declared checks of dataclass instance ``obj`` on its values, storing what they
    return (frozen instances too: for __post_init__). A bad value raises the check's one-line
    error, named by the field (or by its flag, flags=True)."""
    cls = type(obj)
    for f in _declared(cls):
        key = flag_of(cls, f.name) if flags else f.name
        object.__setattr__(obj, f.name, f.metadata["check"](key, getattr(obj, f.name)))


def _brief(v) -> str:
    """repr(v) on one line, at most 80 characters (an array's repr spans lines)."""
    text = " ".join(repr(v).split())
    return text if len(text) <= 80 else text[:77] + "..."


def array(shape: tuple | None = None, *, finite: bool = True, nan: bool = False, lo: float | None = None,
          lo_open: bool = False, copy: bool = True, what: str | None = None) -> Check:
    """A read-only float array (anything np.asarray takes), of ``shape`` if given (-1 for any
    length on that axis; a leading ``...`` for any number of leading axes, e.g. (..., -1, 3)),
    finite unless finite=False (NaN only with nan=True), every element >= lo (> lo if lo_open)
    if given. copy=False: a read-only view of the caller's float array where it is one (no copy:
    for a model built every step)."""
    batch = shape is not None and len(shape) > 0 and shape[0] is Ellipsis
    tail = tuple(shape[1:]) if batch else shape
    if what is None:
        shown = None if shape is None else "(" + ", ".join("..." if s is Ellipsis else str(s) for s in shape) + \
            ("," if len(shape) == 1 else "") + ")"
        what = ("a finite " if finite else "a ") + "numeric array" + ("" if shape is None else f" of shape {shown}") + \
            ("" if lo is None else f" {'>' if lo_open else '>='} {lo:g}")

    scan = finite or not nan or lo is not None  # a check of the values (none: shape only)

    def ok(a) -> bool:
        if a.ndim == 0:  # a scalar: without numpy's reductions (a model built every step)
            x = float(a)
            return not ((finite and not math.isfinite(x)) or (not nan and x != x) or
                        (lo is not None and (x <= lo if lo_open else x < lo)))
        if finite:
            if not np.isfinite(a).all():
                return False
        elif not nan and np.isnan(a).any():
            return False
        return lo is None or not (a <= lo if lo_open else a < lo).any()

    def test(v):
        try:
            a = np.array(v, dtype=float) if copy else np.asarray(v, dtype=float)
        except (TypeError, ValueError):
            raise ParamError("", f"expected {what}, got {_brief(v)}") from None
        if tail is not None and ((a.ndim < len(tail) if batch else a.ndim != len(tail)) or
                                 any(s not in (-1, n) for s, n in zip(tail, a.shape[a.ndim - len(tail):]))):
            raise ParamError("", f"expected {what}, got shape {a.shape}")
        if scan and not ok(a):
            raise ParamError("", f"expected {what}, got {_brief(v)}")
        if copy:
            a.setflags(write=False)
        else:
            a = a.view()
            a.flags.writeable = False
        return a

    return Check(test)


def vec3(what: str | None = None) -> Check:
    """A finite 3-vector (a float array of shape (3,))."""
    return array((3,), what=what or "a finite 3-vector")


def reworded(check, text: str):
    """``check`` whose failure reads ``key: key <text>, got <value>``: for a parameter whose
    error message callers already match (e.g. "n must be a positive integer"). A plain
    check(key, value) function (for validate; no text parser)."""
    def worded(key, value):
        try:
            return check(key, value)
        except ParamError:
            raise ParamError(key, f"{key} {text}, got {value!r}") from None

    return worded


def require(condition: bool, key: str, reason: str) -> None:
    """A rule between fields: ParamError(key, reason) unless ``condition``."""
    if not condition:
        raise ParamError(key, reason)
