"""The components' parameters, built from a scenario by the composition root.

The ground station's sonde tracker is tuned to the world's models (the sonde's kinematics and
wind profile, the relay's and the radar's error processes: a matched-model tracker, as the
sonde experiment runs it); those models belong to vehicles and sitl, which the ground station
does not import. So its parameters are derived here and handed over: to GroundStationNode in
its GsConfig (batch, replay) or in the worker spec's ``params`` (a live GS process).
"""
from __future__ import annotations

import dataclasses


def sonde_tracker_params(scn):
    """The live sonde tracker's SondeTrackerParams for scenario ``scn`` (the fused tracker of
    the sonde experiment at the scenario's rate, radar site and integrity setting)."""
    from sitl.app.experiments.sonde import SondeScenario, tracker_params

    s = scn.sonde
    world = SondeScenario(dt_s=1.0 / scn.run.rate_hz, gcpp_offset_m=s.gcpp_offset_m, gcpp_bearing_deg=s.gcpp_bearing_deg,
                          wind_scale=s.wind_scale, integrity="on" if scn.ground_station.integrity else "off")
    return tracker_params(world, "fused")


def gs_config(scn):
    """The GroundStationNode configuration of scenario ``scn``, with its sonde tracker's parameters."""
    from ground_station.node import GsConfig

    return GsConfig.from_scenario(scn, sonde_tracker_params(scn) if scn.sonde.enabled else None)


def gs_spec_params(scn) -> dict:
    """The ``params`` of a live GS worker's spec: what gs_config adds to the scenario, as JSON."""
    return {"sonde_tracker": dataclasses.asdict(sonde_tracker_params(scn))} if scn.sonde.enabled else {}
