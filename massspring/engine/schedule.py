"""``Schedule``: a model's ``Controls`` written into its run's fields, interval by interval."""

from __future__ import annotations

import math

import numpy as np

from massspring.kernels import state as state_kernels
from massspring.model import feedback


class Schedule:
    """Writes each interval's pin velocities (``dev.pin_velocity``), wind (``dev.wind``)
    and rest lengths (``dev.l0``) of ``model.controls`` (``massspring.model.controls``) before
    a run's steps enter it. ``model`` is the model the kernels step (renumbered where
    the run renumbers); ``dt`` must divide the interval (ValueError naming ``dt``); None
    for an error-controlled run, whose steps land on the intervals' ends (``at``, ``end``).

    ``feedback`` (optional): called as ``feedback(s)`` when the run enters interval s < S
    whose values it has not chosen yet, it returns the values of the controls its
    controller drives (``model.feedback.outputs``: "rest_lengths", "wind", "pin_targets"
    with rows in this model's order of pins), which replace the model's for that interval
    (``values``; ``pins`` the pins' velocities; ``chosen`` the intervals chosen).
    ``freeze()`` keeps the values chosen so far and calls ``feedback`` no more (a
    gradient's runs again from kept states). ``serial``: the run's loops are serial (its
    writes then run on one thread)."""

    def __init__(self, model, dev, dt, feedback=None, serial=False):
        controls = model.controls
        self.controls = controls
        self.per = None if dt is None else controls.steps_per_interval(dt)
        self.count = controls.intervals
        self.dev = dev
        self.applied = None
        self.n = model.n_particles
        self.fixed = model.fixed
        self.pins = None
        if controls.pin_targets is not None and model.has_fixed:
            self.pins = controls.pin_velocities(model.positions[model.fixed])
        self.rest = None
        if controls.rest_lengths is not None and controls.springs.size:
            self.rest = model.rest_lengths.astype(np.float64)
        self.values = {name: getattr(controls, name).copy() for name in ("wind", "rest_lengths", "pin_targets")
                      if getattr(controls, name) is not None}
        self.start = model.positions[model.fixed]  # the pins' positions at time 0
        self.feedback = feedback
        self.chosen = set()
        self.serial = serial

    def freeze(self):
        """Call ``feedback`` no more: the values chosen so far are the run's."""
        self.feedback = None

    def snapshot(self):
        """The intervals chosen so far (their values stay in ``values``)."""
        return frozenset(self.chosen)

    def restore(self, chosen):
        """Back to a ``snapshot()``: intervals chosen since are chosen again when entered."""
        self.chosen = set(chosen)
        self.applied = None

    def forget(self, t):
        """Intervals from the one holding time ``t`` (s) on are chosen again when entered
        (a run set to another state there); nothing once frozen."""
        if self.feedback is not None:
            first = self.at(t)
            self.chosen = {s for s in self.chosen if s < first}
            self.applied = None

    def interval(self, step) -> int:
        """The interval step ``step`` (from 0) is in; ``count`` and above: after the last."""
        return min(step // self.per, self.count)

    def at(self, t) -> int:
        """The interval the step from time ``t`` (s) is in (``count`` and above: after the last)."""
        return min(int(math.floor(t / self.controls.interval + 1e-9)), self.count)

    def before(self, t) -> int:
        """The interval of a step that ended at time ``t`` (s) > 0."""
        return min(max(math.ceil(t / self.controls.interval - 1e-9) - 1, 0), self.count)

    def end(self, t) -> float:
        """The end (s) of the interval the step from ``t`` is in (inf after the last)."""
        s = self.at(t)
        return math.inf if s >= self.count else (s + 1) * self.controls.interval

    def steps_left(self, step) -> int:
        """Steps from ``step`` to the next interval's first (None after the last)."""
        if step // self.per >= self.count:
            return None
        return (step // self.per + 1) * self.per - step

    def apply(self, step, t=None):
        """The fields for the step from ``step`` (its interval's values; from time ``t``, s,
        where given), if not already there."""
        s = self.interval(step) if t is None else self.at(t)
        if s == self.applied:
            return
        if self.feedback is not None and s < self.count and s not in self.chosen:
            for name, value in self.feedback(s).items():
                self.values[name][s] = value
                if name == "pin_targets" and self.pins is not None:  # the interval's pin velocity
                    before = self.start if s == 0 else self.values["pin_targets"][s - 1]
                    self.pins[s] = (value - before) / self.controls.interval
            self.chosen.add(s)
        held = min(s, self.count - 1)  # wind and rest lengths keep their last values
        if self.pins is not None:
            velocities = np.zeros((self.n, 3))
            if s < self.count:  # after the last interval the pins stay at their last targets
                velocities[self.fixed] = self.pins[s]
            state_kernels.load_vectors(self.dev.pin_velocity, velocities)
        if "wind" in self.values:
            self.dev.wind[None] = self.values["wind"][held].tolist()
        if self.rest is not None:
            self.rest[self.controls.springs] = self.values["rest_lengths"][held]
            state_kernels.load_reals(self.dev.l0, self.rest, self.serial)
        self.applied = s


class ControlShares:
    """The controls' gradients (``massspring.model.controls``), interval by interval: after the
    adjoint of an interval's first step, what the steps since the last such read added to
    the wind's, rest lengths' and pin velocities' accumulators is that interval's share
    (steps after the last interval add to its wind and rest lengths; pins then stand still)."""

    def __init__(self, sim, adj):
        self.sim, self.adj = sim, adj
        self.schedule = sim.schedule
        self.controls = sim.model.controls
        count = self.controls.intervals
        self.wind = np.zeros((count, 3))
        self.rest = np.zeros((count, 0 if self.controls.springs is None else self.controls.springs.size))
        self.pins = np.zeros((count, sim.model.fixed.size, 3))
        self.seen = self._totals()
        self.controller = sim.controller
        self.states = sim.control_states
        self.parameters = {} if self.controller is None else {
            name: np.zeros(np.shape(value)) for name, value in self.controller.parameters.items()}

    def _totals(self):
        """The accumulators of the controls the model has (zeros for the others: not read)."""
        n, m = self.sim.model.n_particles, self.sim.model.n_springs
        controls = self.controls
        wind = self.adj.read("gwind", n).sum(axis=0) if controls.wind is not None else np.zeros(3)
        rest = np.zeros(m)
        if m and controls.rest_lengths is not None:
            state_kernels.read_reals(self.adj.gl0, rest, self.schedule.serial)
        pins = self.adj.read("gp", n) if controls.pin_targets is not None else np.zeros((n, 3))
        return wind, rest, pins

    def after(self, k, t=None, t_before=None):
        """Called after step k's adjoint (of a replayed run: the step from time ``t``, s,
        the one before it from ``t_before``)."""
        if t is None:
            if k % self.schedule.per:
                return
            s = self.schedule.interval(k)
        else:
            s = self.schedule.at(t)
            if k and self.schedule.at(t_before) == s:
                return
        totals = self._totals()
        wind, rest, pins = (now - before for now, before in zip(totals, self.seen))
        self.seen = totals
        held = min(s, self.controls.intervals - 1)
        self.wind[held] += wind
        if self.rest.shape[1]:
            self.rest[held] += rest[self.schedule.controls.springs]
        if s < self.controls.intervals:
            self.pins[s] += self.sim.to_user(pins)[self.sim.model.fixed]
        if s in self.states:
            self._through_controller(s)

    def _through_controller(self, s):
        """Interval s's shares through the feedback controller that chose its values
        (``model.feedback``): into its parameters, and into dL/dx, dL/dv of the state it
        read (the adjoint's ``lx``, ``lv`` at the interval's start; pinned rows dropped
        unless it drives the pins, whose targets' share is the difference of the shares of
        the velocities of intervals s and s + 1 over the interval)."""
        cotangents = {}
        for name in self.controller.drives:
            if name == "pin_targets":  # P_s sets the velocity of intervals s (+) and s + 1 (-)
                later = self.pins[s + 1] if s + 1 < self.controls.intervals else 0.0
                cotangents[name] = (self.pins[s] - later) / self.controls.interval
            else:
                cotangents[name] = (self.wind if name == "wind" else self.rest)[s].copy()
        params, dx, dv = feedback.pullback(self.controller, self.states[s], cotangents)
        for name, share in params.items():
            self.parameters[name] += share
        dx, dv = dx.copy(), dv.copy()
        if "pin_targets" not in self.controller.drives:  # else they go back through the pins' motion
            fixed = self.sim.model.fixed
            dx[fixed] = dv[fixed] = 0.0
        state_kernels.add_vector_pair(self.adj.lx, self.adj.lv, np.ascontiguousarray(self.sim.to_inner(dx)),
                                      np.ascontiguousarray(self.sim.to_inner(dv)), self.schedule.serial)

    def gradients(self, lv):
        """name -> gradient of each control; ``lv`` dL/dv of the initial state (n, 3), whose
        pinned rows are the first interval's pin velocity's share."""
        pins = self.pins.copy()
        if self.controller is None or "pin_targets" not in self.controller.drives:  # else the start's are constants
            pins[0] += self.sim.to_user(lv)[self.sim.model.fixed]
        grads = {"controls.wind": self.wind.copy(), "controls.rest_lengths": self.rest.copy()}
        grads.update({f"controller.{name}": value.copy() for name, value in self.parameters.items()})
        if self.controls.pin_targets is not None:
            grads["controls.pin_targets"] = self.controls.pin_target_gradient(pins)
        return grads
