"""Parameters declared once, for the composition root: the TOML form of a section and the
command-line flags (with their --help texts) of the same declarations. The declaration core
(param, the Check objects, validate, require) is filters.params, the lowest layer, so that the
world, the components and the filters declare their parameters the same way; it is re-exported
here.

    @dataclass(frozen=True)
    class RunSection:
        seed: int = param(1, check=lambda k, v: integer(k, v, lo=0), doc="seed of every random draw")

``checks(cls)`` gives {name: check(key, value) -> stored value}, ``docs(cls)`` {name: doc},
``toml_table(name, obj)`` the section as documented TOML (its values, each key preceded by its
doc as a comment). The checks raise the caller's error type (a scenario's ScenarioError): they
are the caller's functions; this module only carries them.
"""
from __future__ import annotations

import json
import math
import textwrap
from dataclasses import MISSING

from filters.params import (Check, ParamError, _declared, array, as_given, checks, choice, default_of,  # noqa: F401
                            docs, flag_of, from_text, instance_of, integer, number, optional, param, require,
                            several, string, switch, validate, vec3)

__all__ = ["param", "checks", "docs", "toml_value", "toml_table", "ParamError", "Check", "integer", "number",
           "choice", "switch", "string", "optional", "several", "from_text", "cli_type", "default_of", "flag_of",
           "add_flags", "options_from_args", "validate", "help_text", "require", "array", "vec3",
           "instance_of", "as_given", "quiet_option", "backend_option"]


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


def quiet_option():
    """The ``--quiet`` switch of every long command (a fresh field per options class)."""
    return param(False, check=switch(), doc="no progress lines")


def backend_option(doc: str = "covariance kernels: compiled (numba) or plain numpy"):
    """The ``--backend auto|numba|numpy`` choice of the compiled commands (a fresh field per class)."""
    return param("auto", check=choice("auto", "numba", "numpy"), doc=doc)

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


