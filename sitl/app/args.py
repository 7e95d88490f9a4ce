"""The command line's vocabulary: the usage error (one line, exit 2), the parser that raises it
instead of printing argparse's usage block, and argument types that reject bad values with a
one-line reason. A leaf of the composition root: the experiments and benches import it, not
the command line itself (which imports them)."""
from __future__ import annotations

import argparse
import os
from pathlib import Path

from sitl.params import cli_type, from_text, integer, number

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
