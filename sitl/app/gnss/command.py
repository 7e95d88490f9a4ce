"""The `gnss` command group: ``add_parser(subparsers)`` registers it on the `skyfuse` parser,
``main(args)`` runs the chosen subcommand. A subcommand is a sibling module with ``DOC``,
``add_args(parser)`` and ``main(args)``; add its name and loader to ``SUBCOMMANDS`` (the loader
imports it lazily, so that `skyfuse --help` stays light)."""
from __future__ import annotations

from sitl.app.args import Parser, UsageError


def _orbits():
    from sitl.app.gnss import orbits

    return orbits


# name -> (loader of its module, one-line help)
def _export():
    from sitl.app.gnss import export

    return export


def _solve():
    from sitl.app.gnss import solve

    return solve


SUBCOMMANDS = {
    "orbits": (_orbits, "broadcast GPS/GLONASS orbits and clocks against IGS precise orbits (SP3) and clocks"),
    "solve": (_solve, "real GPS L1 observations through the seed 000 filter, against RTKLIB and dual-frequency iono"),
    "export": (_export, "the simulated world as RINEX 3.04 observation and navigation files plus truth"),
}


def add_parser(subparsers) -> None:
    """Add `gnss` and its subcommands to the `skyfuse` subparsers."""
    g = subparsers.add_parser("gnss", help="real GNSS files: RINEX/SP3 readers, broadcast orbits against IGS",
                              description="Real GNSS data: RINEX observation/navigation, SP3 and clock files.")
    g.set_defaults(gnss_main=main)
    sub = g.add_subparsers(dest="gnss_command", metavar="SUBCOMMAND", parser_class=Parser)
    sub.required = True
    for name, (load, doc) in SUBCOMMANDS.items():
        sub.add_parser(name, help=doc, description=doc, flags=lambda p, _load=load: _load().add_args(p))


def main(args) -> int:
    entry = SUBCOMMANDS.get(getattr(args, "gnss_command", None))
    if entry is None:
        raise UsageError(f"skyfuse gnss: unknown subcommand {args.gnss_command!r}")
    return entry[0]().main(args)
