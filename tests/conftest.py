"""Suite-wide settings for running under pytest-xdist (pyproject's addopts: `-n 2`).

Each worker keeps its own hypothesis example database, so two processes never write one
directory at once; a test that failed replays its failing example on a re-run in the
worker that runs it (with `-n 0`, the usual `.hypothesis/examples`)."""
from __future__ import annotations

import os
import sys
import types

from hypothesis import settings
from hypothesis.database import DirectoryBasedExampleDatabase

# `tests` is the package of the shared helpers (tests.procs, tests.outputs, tests.helpers,
# tests.mavlink_peer) and of the test modules others import from (tests.sitl.bus.test_bus), with
# neither tests/ nor the checkout on sys.path (pyproject: --import-mode=importlib), so the tests
# import the installed package and pytest's module of a file is the one its importers get.
_tests = sys.modules.get("tests")
if getattr(_tests, "__path__", None) is None:
    _tests = sys.modules["tests"] = types.ModuleType("tests", "skyfuse's test suite")
    _tests.__path__ = [os.path.dirname(os.path.abspath(__file__))]

_WORKER = os.environ.get("PYTEST_XDIST_WORKER")
if _WORKER:
    settings.register_profile(
        "xdist-worker", database=DirectoryBasedExampleDatabase(os.path.join(".hypothesis", f"examples-{_WORKER}")))
    settings.load_profile("xdist-worker")
