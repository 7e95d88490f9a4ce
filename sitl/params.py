"""Parameters declared once: a dataclass field that carries its default, its check and its
documentation, from which the validation, the documented default file and the docs come.

    @dataclass(frozen=True)
    class RunSection:
        seed: int = param(1, check=lambda k, v: integer(k, v, lo=0), doc="seed of every random draw")

``checks(cls)`` gives {name: check(key, value) -> stored value}, ``docs(cls)`` {name: doc},
``toml_table(name, obj)`` the section as documented TOML (its values, each key preceded by its
doc as a comment). The checks raise the caller's error type (a scenario's ScenarioError): they
are the caller's functions; this module only carries them.
"""
from __future__ import annotations

import dataclasses
import json
import math
import textwrap
from dataclasses import MISSING

__all__ = ["param", "checks", "docs", "toml_value", "toml_table", "ParamError", "Check", "integer", "number",
           "choice", "switch", "string", "optional", "several", "from_text", "cli_type", "default_of", "flag_of",
           "add_flags", "options_from_args", "validate", "help_text"]


def param(default=MISSING, *, check, doc: str, default_factory=MISSING, flag=None, metavar=None,
          cli=True, shown=None, note="", default_help=None):
    """A dataclass field with its check (key, value) -> value and its one-paragraph doc.

    For an option on the command line (add_flags): ``flag`` (default --name-with-dashes),
    ``metavar``, ``cli=False`` to keep it off the command line; the --help text is the doc then
    "(default X<note>)", X the default or ``shown`` (a text or a callable giving the value that
    stands for a None default, e.g. another dataclass's declared default), or ``default_help``
    instead of that parenthesis."""
    if not doc or not callable(check):
        raise TypeError("param: a check and a doc are required")
    md = {"check": check, "doc": " ".join(doc.split())}
    extra = {"flag": flag, "metavar": metavar, "shown": shown, "default_help": default_help}
    md.update({k: v for k, v in extra.items() if v is not None})
    if note:
        md["note"] = note
    if not cli:
        md["cli"] = False
    return dataclasses.field(default=default, default_factory=default_factory, metadata=md)


def _declared(cls):
    return [f for f in dataclasses.fields(cls) if "check" in f.metadata]


def checks(cls) -> dict:
    """{field name: check} of the declared parameters of dataclass ``cls``, in declaration order."""
    return {f.name: f.metadata["check"] for f in _declared(cls)}


def docs(cls) -> dict:
    """{field name: doc} of the declared parameters of dataclass ``cls``."""
    return {f.name: f.metadata["doc"] for f in _declared(cls)}


def toml_value(v) -> str:
    """v as a TOML value: booleans, integers, floats (exact: repr), strings, tuples as arrays."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            raise ValueError(f"toml_value: {v!r} has no TOML form here")
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)  # a TOML basic string for these texts
    if isinstance(v, (tuple, list)):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    raise TypeError(f"toml_value: {type(v).__name__} has no TOML form")


def toml_table(name: str, obj, width: int = 96) -> str:
    """The section ``[name]`` of the values of dataclass instance ``obj``, each declared key
    preceded by its doc as comment lines."""
    out = [f"[{name}]"]
    for f in _declared(type(obj)):
        out += textwrap.wrap(f.metadata["doc"], width - 2, initial_indent="# ", subsequent_indent="# ")
        out.append(f"{f.name} = {toml_value(getattr(obj, f.name))}")
    return "\n".join(out)


# ---------------------------------------------------------------- checks that also read text
# A Check is a declared parameter's check, callable as check(key, value) -> value (a ParamError,
# one line "key: expected ..., got ...", when the value is bad), that can also read the value
# from a command-line word (check.parse(text)) and tells argparse how the flag takes it
# (check.cli: choices, action, nargs). The experiments' and benches' options are declared with
# these; the command line's argument types (sitl.app.args.positive_int, ...) are made of them.


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


def integer(lo: int | None = None, hi: int | None = None, what: str | None = None) -> Check:
    """An integer (not a bool) in [lo, hi]; from text, int(text)."""
    if what is None:
        what = {1: "a positive integer", 0: "an integer >= 0"}.get(lo, "an integer") if hi is None else \
            f"an integer in {lo}..{hi}"
        if lo not in (None, 0, 1) and hi is None:
            what = f"an integer >= {lo}"

    def test(v):
        if isinstance(v, bool) or not isinstance(v, int):
            raise ParamError("", f"expected {what}, got {v!r}")
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            raise ParamError("", f"expected {what}, got {v}")
        return v

    def parse(text):
        try:
            v = int(text)
        except ValueError:
            raise ParamError("", f"expected {what}, got {text!r}") from None
        return test(v)

    return Check(test, parse)


def number(lo: float | None = None, *, lo_open: bool = False, finite: bool = True, what: str | None = None) -> Check:
    """A float (an int is taken as one), finite unless finite=False, and >= lo (> lo if lo_open);
    from text, float(text)."""
    if what is None:
        what = "a positive finite number" if (lo == 0 and lo_open) else \
            ("a finite number" if finite else "a number") + ("" if lo is None else f" {'>' if lo_open else '>='} {lo:g}")
    loose = what.replace("positive finite", "positive").replace("finite ", "")  # a word that is no number

    def ok(x):
        return not ((finite and not math.isfinite(x)) or x != x or
                    (lo is not None and (x <= lo if lo_open else x < lo)))

    def test(v):
        if isinstance(v, bool) or not isinstance(v, (int, float)):
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


def switch() -> Check:
    """A boolean: a flag that sets it (store_true; the default is False)."""
    def test(v):
        if not isinstance(v, bool):
            raise ParamError("", f"expected true or false, got {v!r}")
        return v

    return Check(test, cli={"action": "store_true"})



def quiet_option():
    """The ``--quiet`` switch of every long command (a fresh field per options class)."""
    return param(False, check=switch(), doc="no progress lines")


def backend_option(doc: str = "covariance kernels: compiled (numba) or plain numpy"):
    """The ``--backend auto|numba|numpy`` choice of the compiled commands (a fresh field per class)."""
    return param("auto", check=choice("auto", "numba", "numpy"), doc=doc)

def string() -> Check:
    """Any string."""
    def test(v):
        if not isinstance(v, str):
            raise ParamError("", f"expected a string, got {v!r}")
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


def cli_type(check: Check):
    """``check`` as an argparse type: text -> value, or ArgumentTypeError(the one-line reason)."""
    import argparse

    def parse(text: str):
        try:
            return check.parse(text)
        except ParamError as exc:
            raise argparse.ArgumentTypeError(exc.reason) from None

    parse.__name__ = getattr(check, "__name__", "value")
    return parse


# ---------------------------------------------------------------- options: declared once
# An experiment's (a bench's) options are one frozen dataclass whose fields are declared with
# param(...) and a Check: add_flags gives its argparse flags (the flag --name-with-dashes unless
# param(flag=...), the doc as --help text with the default appended, the check as argument type),
# options_from_args the instance of the parsed flags, validate the checks of an instance.


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


def help_text(f) -> str:
    """The --help text of a declared option: its doc, then its default (or what stands for it)."""
    md = f.metadata
    check = md["check"]
    default = f.default if f.default is not MISSING else \
        (f.default_factory() if f.default_factory is not MISSING else None)
    if md.get("default_help") is not None:
        tail = md["default_help"]
    elif check.cli.get("action") == "store_true":
        tail = ""
    else:
        shown = md.get("shown")
        if callable(shown):
            shown = shown()
        if shown is None:
            shown = default
        tail = "" if shown is None else f"default {shown if isinstance(shown, str) else check.show(shown)}"
        tail += md.get("note", "")
    text = md["doc"] + (f" ({tail})" if tail else "")
    return text.replace("%", "%%")  # argparse formats help texts with %


def add_flags(parser, cls) -> None:
    """The argparse flags of the declared options of dataclass ``cls`` (dest = the field name)."""
    for f in _declared(cls):
        md = f.metadata
        if not md.get("cli", True):
            continue
        check = md["check"]
        if not isinstance(check, Check):
            raise TypeError(f"{cls.__name__}.{f.name}: a command-line option needs a sitl.params.Check")
        kw = {"dest": f.name, "help": help_text(f), **check.cli}
        if kw.get("action") != "store_true":
            kw["default"] = default_of(cls, f.name)
            if "choices" not in kw:
                kw["type"] = cli_type(check)
            if md.get("metavar") is not None:
                kw["metavar"] = md["metavar"]
        parser.add_argument(flag_of(cls, f.name), **kw)


def options_from_args(cls, ns):
    """The instance of ``cls`` of the parsed flags ``ns`` (an argparse Namespace)."""
    return cls(**{f.name: getattr(ns, f.name) for f in _declared(cls) if hasattr(ns, f.name)})


def validate(obj, flags: bool = False) -> None:
    """Run the declared checks of dataclass instance ``obj`` on its values, storing what they
    return (frozen instances too: for __post_init__). A bad value raises the check's one-line
    error, named by the field (or by its flag, flags=True)."""
    cls = type(obj)
    for f in _declared(cls):
        key = flag_of(cls, f.name) if flags else f.name
        object.__setattr__(obj, f.name, f.metadata["check"](key, getattr(obj, f.name)))
