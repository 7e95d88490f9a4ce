"""The worker-process runtime a component process runs on (worker.py): its spec, its bus
session, its line protocol with the supervisor, its pacing by sitl.pacing.

Workers are started by module name with subprocess (never fork: a Zenoh session does not
survive a fork): ``python -m vehicles.process SPEC.json`` and ``python -m
ground_station.process SPEC.json`` with a spec written by `sitl.scenario.worker_specs`. The
supervisor, the status line, the scoring and the launcher that start them are the composition
root's (sitl.app).
"""
