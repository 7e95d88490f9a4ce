"""Suite-wide settings for running under pytest-xdist (pyproject's addopts: `-n 2`).

Each worker keeps its own hypothesis example database, so two processes never write one
directory at once; a test that failed replays its failing example on a re-run in the
worker that runs it (with `-n 0`, the usual `.hypothesis/examples`)."""
from __future__ import annotations

import os

from hypothesis import settings
from hypothesis.database import DirectoryBasedExampleDatabase

_WORKER = os.environ.get("PYTEST_XDIST_WORKER")
if _WORKER:
    settings.register_profile(
        "xdist-worker", database=DirectoryBasedExampleDatabase(os.path.join(".hypothesis", f"examples-{_WORKER}")))
    settings.load_profile("xdist-worker")
