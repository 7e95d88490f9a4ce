"""The command line's vocabulary: the usage error (one line, exit 2), the parser that raises it
instead of printing argparse's usage block, and argument types that reject bad values with a
one-line reason. A leaf of the composition root: the experiments and benches import it, not
the command line itself (which imports them)."""
from __future__ import annotations

import argparse
import os
from pathlib import Path

from sitl.params import Check, ParamError, cli_type, from_text, help_text, integer, number, options_from_args

EXIT_USAGE = 2


class UsageError(Exception):
    """A bad input from the user: reported as one line, exit status 2."""


class Parser(argparse.ArgumentParser):
    """argparse's parser, with a usage error of one line, and flags added when first needed:
    Parser(flags=add) calls add(parser) before the parser parses or prints its help (a
    subcommand's flags come from its module, imported only when that subcommand is used)."""

    def __init__(self, *args, flags=None, **kwargs):
        self._deferred_flags = flags
        super().__init__(*args, **kwargs)

    def _add_deferred_flags(self) -> None:
        add, self._deferred_flags = self._deferred_flags, None
        if add is not None:
            add(self)

    def parse_known_args(self, args=None, namespace=None):
        self._add_deferred_flags()
        return super().parse_known_args(args, namespace)

    def format_help(self):
        self._add_deferred_flags()
        return super().format_help()

    def format_usage(self):
        self._add_deferred_flags()
        return super().format_usage()

    def error(self, message: str):  # argparse's default prints the whole usage block
        raise UsageError(f"{self.prog}: {message}")


# --- argument types: each rejects bad values with a one-line reason ----------------------
# Each is a declared check of sitl.params (the one definition: the options' dataclasses declare
# their fields with the same checks) read as an argparse type.

def int_at_least(lowest: int, what: str):
    return cli_type(integer(lo=lowest, what=what))


positive_int = cli_type(integer(lo=1))
nonnegative_int = cli_type(integer(lo=0))
positive_float = cli_type(number(0, lo_open=True))
nonnegative_float = cli_type(number(0))
finite_float = cli_type(number())


def output_dir(text: str) -> Path:
    """An output directory: created if missing, and it must be writable."""
    path = Path(text)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise argparse.ArgumentTypeError(f"cannot create output directory {text!r}: {exc.strerror}") from None
    if not path.is_dir():
        raise argparse.ArgumentTypeError(f"output path {text!r} is not a directory")
    if not os.access(path, os.W_OK | os.X_OK):
        raise argparse.ArgumentTypeError(f"output directory {text!r} is not writable")
    return path


def output_file(text: str) -> Path:
    path = Path(text)
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        raise argparse.ArgumentTypeError(f"directory of {text!r} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise argparse.ArgumentTypeError(f"directory of {text!r} is not writable")
    return path


# the checks of the options' declarations (sitl.params.param) that the command line reads
OUTPUT_DIR = from_text(output_dir)
OUTPUT_FILE = from_text(output_file)


# --- what add_flags does not give: a repeatable flag, positional arguments -------------------

def repeatable(check: Check) -> Check:
    """A flag given any number of times (argparse's append): None when it is not given, else the
    list of its values, each one that ``check`` takes."""
    def test(v):
        if v is None:
            return None
        if not isinstance(v, (list, tuple)):
            raise ParamError("", f"expected a list of values, got {v!r}")
        return [check("", x) for x in v]

    return Check(test, check.parse, cli={**check.cli, "action": "append"}, show=check.show)


def add_positional(parser, cls, name: str) -> None:
    """The positional argument of option ``name`` of dataclass ``cls``: declared like a flag
    (sitl.params.param with its check and doc) and cli=False, since add_flags gives flags only
    (argparse takes no dest= for a positional)."""
    from dataclasses import fields

    f = next(f for f in fields(cls) if f.name == name)
    check = f.metadata["check"]
    kw = {"help": help_text(f), **check.cli}
    if "choices" not in kw:
        kw["type"] = cli_type(check)
    if f.metadata.get("metavar") is not None:
        kw["metavar"] = f.metadata["metavar"]
    parser.add_argument(name, **kw)


def options_of(cls, ns):
    """The options instance of the parsed command line ``ns`` (sitl.params.options_from_args); a
    value its declaration refuses (one built by a caller, not by argparse) is a UsageError."""
    try:
        return options_from_args(cls, ns)
    except ParamError as exc:
        raise UsageError(str(exc)) from None
