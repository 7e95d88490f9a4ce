"""The composition root: the one part of skyfuse that wires components together.

``sitl.app`` holds the command line (`skyfuse`, cli.py), the live launcher and its supervisor
(launcher.py, supervisor.py, status.py, scoring.py, preflight.py, live_faults.py, the
`skyfuse fault` command in fault_cli.py), the batch run (batch.py), the experiments
(experiments/) and the benchmarks (bench/). It imports the components -- vehicles and
ground_station -- statically, builds their parameters and hands them over in the worker spec or
the constructor. Nothing outside this package imports it (the import contract in pyproject.toml).
"""
