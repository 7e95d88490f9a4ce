"""The swarm with its autopilots in the loop: the scenario's flight until a GCS commands.

:class:`AutopilotSwarm` wraps the vehicle process's swarm (a vehicles.uav KinematicSwarm with
the scenario's law) and an :class:`~vehicles.autopilot.core.Autopilot` for the same UAVs.  Each
``step(t_s)``:

1. steps the autopilot at the interval's start with every UAV's kinematic state;
2. steps the scenario's swarm as before (``swarm.step(t_s)``: the compiled integrator, the same
   numbers): the UAVs whose guidance is SCENARIO take their truth from it -- so a run without a
   GCS command is bit-for-bit the run without the autopilot;
3. integrates every other UAV ("detached": one the autopilot flies, from the state it had when
   it left the scenario's flight) with vehicles.uav.propagate on
   :class:`~vehicles.autopilot.guidance.AutopilotLaw` (the same RK4 and ODE; the numpy path);
4. returns the VehicleTruth of all N UAVs; ``events`` holds the autopilot's events of the step.

A detached UAV stays detached (its state is its own); when AUTO flies the scenario's pattern
again (a mission cleared) it takes the scenario law's commands from where it is, for the laws
this module can cut to a subset (SinusoidalLaw, Racetrack, Hold); for other laws it has no
pattern any more (AUTO without a mission then returns it home, as ArduPlane does).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from vehicles import uav

from . import guidance as gd
from .config import AutopilotConfig
from .core import Autopilot, Event


def subset_law(law, idx):
    """The scenario law for UAVs idx only (None if this law cannot be cut)."""
    idx = np.asarray(idx)
    if isinstance(law, uav.Hold):
        return uav.Hold((int(idx.size),))
    if isinstance(law, (uav.SinusoidalLaw, uav.Racetrack)):
        kw = {}
        for f in dataclasses.fields(law):
            if not f.init:
                continue
            v = getattr(law, f.name)
            kw[f.name] = np.asarray(v)[idx] if f.name in law._FIELDS else v
        return type(law)(**kw)
    return None


class AutopilotSwarm:
    """The swarm (scenario law) + the autopilots (module docstring).

    swarm: a vehicles.uav KinematicSwarm (its ``n``, ``state``, ``dt_s``, ``ell``, ``guidance``);
    autopilot: the Autopilot of the same N UAVs (default: every UAV armed in AUTO in flight,
    flying the scenario's pattern, home at its start); dt_s: the RK4 step of the detached
    UAVs (default the swarm's); ap_step_s: the autopilot is stepped at least this often
    within one ``step`` (None: once per step)."""

    def __init__(self, swarm, autopilot: Autopilot | None = None, *, config: AutopilotConfig | None = None,
                 dt_s: float | None = None, ap_step_s: float | None = None):
        self.swarm = swarm
        st = swarm.state
        y = np.asarray(st.y, float).reshape(-1, 4)
        self.n = y.shape[0]
        self.ap = autopilot if autopilot is not None else Autopilot(y[:, 0], y[:, 1], y[:, 2], y[:, 3], config=config,
                                                                     t0_s=st.t_s, ell=swarm.ell)
        if self.ap.n != self.n:
            raise ValueError(f"autopilot has {self.ap.n} UAVs, the swarm {self.n}")
        self.dt_s = float(swarm.dt_s if dt_s is None else dt_s)
        self.ap_step_s = None if ap_step_s is None else float(ap_step_s)
        self.own = np.zeros(self.n, dtype=bool)
        self.y = y.copy()
        self.t_s = float(st.t_s)
        self.events: list[Event] = []
        self.last_guidance: gd.Guidance | None = None
        self._sub_law = None  # (idx tuple, law) cache of the detached UAVs' scenario law

    @property
    def state_y(self) -> np.ndarray:
        """(N, 4) [lat, lon, h, heading] of every UAV now."""
        if self.own.all():
            return self.y.copy()
        sw = np.asarray(self.swarm.state.y, float).reshape(-1, 4)
        return np.where(self.own[:, None], self.y, sw)

    def _scenario_for(self, idx):
        if not np.any(self.last_guidance.kind[idx] == gd.SCENARIO):
            return None
        key = tuple(idx.tolist())
        if self._sub_law is None or self._sub_law[0] != key:
            self._sub_law = (key, subset_law(self.swarm.guidance, idx))
        return self._sub_law[1]

    def step(self, t_s: float):
        t1 = float(t_s)
        if not t1 >= self.t_s:
            raise ValueError(f"t_s must not go back: {t_s!r} after {self.t_s}")
        ts = [t1]
        if self.ap_step_s is not None and t1 - self.t_s > self.ap_step_s:
            k = int(np.ceil((t1 - self.t_s) / self.ap_step_s - 1e-9))
            ts = list(self.t_s + (t1 - self.t_s) * np.arange(1, k + 1) / k)
            ts[-1] = t1
        events: list[Event] = []
        t0 = self.t_s
        for tb in ts:
            y = self.state_y
            g, ev = self.ap.step(t0, tb - t0, y[:, 0], y[:, 1], y[:, 2], y[:, 3])
            events += ev
            newly = (g.kind != gd.SCENARIO) & ~self.own
            if newly.any():
                self.y[newly] = y[newly]
                self.own |= newly
                if subset_law(self.swarm.guidance, np.flatnonzero(newly)[:1]) is None:
                    self.ap.scenario[newly] = False  # this law cannot fly a subset: no pattern to rejoin
            self._advance(t0, tb, g)
            t0 = tb
        self.t_s = t1
        self.events = events
        if self.own.all():  # nobody flies the scenario's swarm any more: it need not be stepped
            law = gd.AutopilotLaw(self.last_guidance, self._scenario_for(np.arange(self.n)), self.swarm.ell)
            return uav.truth(uav.KinematicState(t1, self.y.copy(), np.zeros(self.n, dtype=int)), law, self.swarm.ell)
        tu = self.swarm.step(t1)
        if not self.own.any():
            return tu
        idx = np.flatnonzero(self.own)
        law = gd.AutopilotLaw(self.last_guidance.subset(idx), self._scenario_for(idx), self.swarm.ell)
        st = uav.KinematicState(t1, self.y[idx].copy(), np.zeros(idx.size, dtype=int))
        tr = uav.truth(st, law, self.swarm.ell)
        out = {f: np.array(getattr(tu, f)) for f in tu._fields[1:]}
        for f in tu._fields[1:]:
            out[f][idx] = np.asarray(getattr(tr, f))
        return tu._replace(**out)

    def _advance(self, t0: float, t1: float, g: gd.Guidance) -> None:
        self.last_guidance = g
        if not self.own.any() or t1 <= t0:
            return
        # a held UAV (speed, climb and turn 0) is a fixed point of the ODE: not integrated, so it
        # stays put exactly (the integrator's longitude wrap would move its last bit)
        idx = np.flatnonzero(self.own & (g.kind != gd.HOLD))
        if not idx.size:
            return
        law = gd.AutopilotLaw(g.subset(idx), self._scenario_for(idx), self.swarm.ell)
        st = uav.KinematicState(t0, self.y[idx].copy(), np.zeros(idx.size, dtype=int))
        st = uav.propagate(st, t1, law, self.dt_s, self.swarm.ell, backend="numpy")
        self.y[idx] = st.y
