"""`skyfuse gnss`: real GNSS files in and out (RINEX, SP3, RINEX clock).

Each subcommand is a sibling module of this package (orbits.py; export.py and solve.py are
added the same way) that declares ``DOC`` (its one-line help), ``add_args(parser)`` and
``main(args) -> int``; command.py lists them in ``SUBCOMMANDS`` and registers the group.
"""
