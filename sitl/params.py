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

__all__ = ["param", "checks", "docs", "toml_value", "toml_table"]


def param(default=MISSING, *, check, doc: str, default_factory=MISSING):
    """A dataclass field with its check (key, value) -> value and its one-paragraph doc."""
    if not doc or not callable(check):
        raise TypeError("param: a check and a doc are required")
    return dataclasses.field(default=default, default_factory=default_factory,
                             metadata={"check": check, "doc": " ".join(doc.split())})


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
