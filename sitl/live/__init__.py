"""The live SITL plumbing: wall-clock pacing (the only place that reads the wall clock or
sleeps), the worker-process runtime, the supervisor, the status line and the launcher.

Workers are started by module name with subprocess (never fork: a Zenoh session does not
survive a fork): ``python -m vehicles.process SPEC.json`` and ``python -m
ground_station.process SPEC.json`` with a spec written by `sitl.scenario.worker_specs`.

Modules: pacer (sim time <-> wall time), worker (the worker side of the line protocol),
supervisor (start / restart / stop the workers), status (the status line), scoring (errors
from truth/** and gs/estimate/**), batch (the same components in one process, simulated time),
launcher (run / demo / replay), ``python -m sitl.live {run,demo,replay,bench}``.
"""
