"""The pass protocol: whatever acts on a run's state between or after the steps of its
integrator. ``Simulation`` holds a list of passes (those of ``PASSES`` a model wants,
``passes.for_model``) and names none of them.

A pass class declares, for a ``Model``:

* ``wanted(model)``: whether a run of it has the pass (else nothing of it is
  allocated or compiled);
* ``bytes(model)``: its fields' bytes as (per particle, per spring) for the run's
  memory estimate (``engine.footprint``), and ``declare(layout, model)`` those fields;
* where ``differentiable``: ``declare_adjoint(layout, model)`` the fields of its run
  backwards in a gradient's adjoint bundle, and ``gradient_bytes(model, checkpoint, integrator)``
  what that run holds on the host (for the gradient's memory check);
* ``name`` (its registry key), ``term`` (its entry in ``Simulation.info()["terms"]``,
  or None), ``stats_property`` (the ``Simulation`` property that returns its
  ``stats()``, or None), ``carried`` (name -> (dtype, shape per particle) of what a
  restart needs of it, as ``Simulation.carried_state`` gives it),
  ``differentiable`` (``gradient`` runs through it; else ``refusal`` names it in the
  ValueError; its run backwards takes each step's own size: a gradient of an
  error-controlled run or of ``dts``).

An instance, built once per run with ``(dev, cfg, model, serial, dt)`` (the device
bundle, its config, the run's model in its inner numbering, serial loops or not, the
step in s), then:

* ``begin(state)`` before each step, ``end(state, t)`` after it (t: the time the step
  ended at, s);
* ``watch_moves()`` / ``moved()``: in an error-controlled run, the particles whose
  velocities it changed at the end of the step just taken, which the run's error
  estimate leaves out (``engine.adaptive``; None by default: it tells nothing);
* ``stats()``: a dict of plain numbers;
* ``carried_state()`` / ``load(state, carried)``: its restart state, out and in
  (``carried`` None: start afresh);
* ``snapshot()`` / ``restore(state, snapshot)``: all of its state before a step, and back
  to it once the run's positions and velocities are back (a rejected step); a pass
  whose state is only its counters keeps this base class's;
* ``adjoint(sim, adj)``: for a gradient's run, an object that runs the pass backwards
  in the steps where it acted (``massspring.gradients``: ``start``, ``any_in``,
  ``before``, ``after``, ``add_gradients``), or None if it never changes the state's
  gradient;
* ``release()``: hand back what it holds beyond the run's bundle.
"""

from __future__ import annotations

import copy


def keep_in_history(integrator, state, n, k):
    """In a gradient's run, where ``integrator`` stored step k's state in its history before
    a pass changed it (``records_history``: in the launch that made it), put the pass's
    ``state`` (n particles) there instead."""
    if integrator.history is not None and integrator.records_history:
        from massspring.kernels import state as state_kernels

        adj, first = integrator.history
        state_kernels.save_state(adj.hx, adj.hv, state, n, k + 1 - first, int(adj.stride[None]))


class Pass:
    """Base class of a pass (see the module docstring)."""

    name = ""
    term = None
    stats_property = None
    carried = {}
    differentiable = False
    refusal = ""  # what gradient's "not built yet" error calls a run with this pass

    @staticmethod
    def wanted(model) -> bool:
        raise NotImplementedError

    @staticmethod
    def bytes(model) -> tuple:
        return (0, 0)

    @staticmethod
    def declare(layout, model):
        """Declare the pass's fields in ``layout`` (a ``device.Layout``)."""

    @staticmethod
    def declare_adjoint(layout, model):
        """Declare the fields of the pass's run backwards in a gradient's adjoint bundle."""

    @staticmethod
    def gradient_bytes(model, checkpoint, integrator) -> int:
        """Host bytes of the pass's run backwards in a gradient whose stretches are
        ``checkpoint`` steps long, with ``integrator`` (its name) stepping."""
        return 0

    def __init__(self, dev, cfg, model, serial, dt):
        self.dev, self.cfg, self.serial, self.dt = dev, cfg, serial, dt

    def begin(self, state):
        """Before a step of ``state``."""

    def end(self, state, t):
        raise NotImplementedError

    def moved(self):
        """The particles (inner numbering, int array) whose velocities this pass changed
        at the end of the step just taken, when it was asked to watch for them
        (``watch_moves``: an error-controlled run, whose estimate leaves them out of the
        steps it spans); None when it does not tell."""
        return None

    def watch_moves(self):
        """From now on, keep what ``moved`` returns (nothing to keep by default)."""

    def stats(self) -> dict:
        return {}

    def carried_state(self) -> dict:
        return {}

    def load(self, state, carried=None):
        """Continue from ``state`` (set by a restart) with ``carried`` (``carried_state()``
        of the saved run, checked by the caller; None: start afresh)."""

    def counters(self) -> dict:
        """The pass's own attributes that count or describe what it did (copied by
        ``snapshot``)."""
        return {}

    def snapshot(self):
        return copy.deepcopy(self.counters()), self.carried_state()

    def restore(self, state, snapshot):
        counters, carried = snapshot
        if self.carried:
            self.load(state, carried)
        for name, value in copy.deepcopy(counters).items():
            setattr(self, name, value)

    def adjoint(self, sim, adj):
        return None

    def release(self):
        """Hand back what the pass holds beyond the run's bundle."""
