"""``python -m sitl.app ...``: the same command line as ``skyfuse`` (sitl/app/cli.py), for a checkout
that is not installed."""
import sys

from sitl.app.cli import main

if __name__ == "__main__":
    sys.exit(main())
