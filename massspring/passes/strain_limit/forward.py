"""Strain limiting: ``Model(strain_limit=s)`` keeps every spring at most (1 + s) times
its rest length after each step, whatever the integrator (``kernels/strain_limit.py``:
Provot-style projections as Jacobi iterations, deterministic). A model without one
declares no field and compiles no kernel of it.

What it changes: positions move along the violated springs by mass-weighted shares and
velocities by the same change over dt (a pinned particle does not move; one moved into
a collider is put back on its surface). Linear momentum is kept to round-off without pins
and colliders (angular momentum is not: the velocity change is applied at the moved
positions); nor is energy: the pass takes away the potential of springs above the
limit and changes velocities by the displacement over dt, which can add or remove
kinetic energy (the drape loses energy at impact with it; the run's energy line says).
"""

from __future__ import annotations

import math

from massspring.passes.base import Pass

ITERATIONS = 500  # at most this many Jacobi iterations a step
TOLERANCE = 1e-4  # violated springs are shortened to limit - this (l / l0 - 1); the pass ends with none past the limit
PASS_BYTES_PER_SPRING = 24  # sl_dx, a vec3 per spring (f64)
PASS_BYTES = 4 + 48  # per particle: sl_k, and the state before the pass (x_sl_before, v_sl_before: f64 vec3s)


def declare(layout, model=None):
    """The pass's fields in ``layout`` (a ``device.Layout``): ``sl_dx`` (a vec3 per spring),
    ``sl_k`` (an i32 per particle) and the state before the pass (``x_sl_before``, ``v_sl_before``)."""
    import taichi as ti

    layout.vectors("sl_dx", layout.real, "spring")
    layout.add("sl_k", ti.i32, "particle")
    layout.vectors("x_sl_before", layout.real)
    layout.vectors("v_sl_before", layout.real)


class StrainLimitPass(Pass):
    """The strain limit of one simulation, run on the state after each step (``end``;
    ``serial``: all its iterations in one serial launch, else one parallel launch each):
    Jacobi iterations until no spring is stretched past the limit, at most
    ``ITERATIONS`` that move particles (then one more launch measures, and moves them
    again if a spring is still over). ``last``: (iterations that moved particles, the
    largest l / l0 - 1 before the pass, the largest after it: at the last launch's start
    where the limit was met, measured after the pass where not) of the last step;
    ``unmet``: steps that ended with a spring still past the limit;
    ``steps``: steps whose pass moved particles; ``most``: the most iterations of a step;
    ``undone``: unmet steps whose pass left the worst spring worse than it found it (the
    pins or colliders hold it: a chain pinned 1.5 times its length apart), and was undone.
    """

    name = "strain-limit"
    stats_property = "strain_limit_stats"
    refusal = "a strain limit"
    differentiable = True

    @staticmethod
    def wanted(model) -> bool:
        return model.has_strain_limit

    @staticmethod
    def bytes(model) -> tuple:
        return (PASS_BYTES, PASS_BYTES_PER_SPRING)

    declare = staticmethod(declare)

    @staticmethod
    def declare_adjoint(layout, model):
        """The fields of its run backwards (``backward.PassSteps``) in a gradient's adjoint
        bundle (float64): the state an iteration starts from (``sl_x``, ``sl_v``), dL/d(an
        iteration's moved positions before the collider projection) (``sl_gy``, a vec3 per
        particle), dL/d(each spring's x_j - x_i) (``sl_gd``, a vec3 per spring) and
        dL/d(its ends' inverse masses) through its correction's share (``sl_gw``, per spring)."""
        for name in ("sl_x", "sl_v", "sl_gy"):
            layout.vectors(name, layout.real)
        layout.vectors("sl_gd", layout.real, "spring")
        layout.add("sl_gw", layout.real, "spring")

    @staticmethod
    def gradient_bytes(model, checkpoint, integrator) -> int:
        """Host bytes of its run backwards: the state before the pass of each step of a
        stretch of ``checkpoint`` steps, and one step's iterations run again."""
        from massspring.passes.strain_limit.backward import host_bytes

        return host_bytes(model.n_particles, checkpoint)

    def __init__(self, dev, cfg, model, serial, dt):
        super().__init__(dev, cfg, model, serial, dt)
        self.limit = model.strain_limit
        self.last = (0, 0.0, 0.0)
        self.unmet = self.steps = self.most = self.undone = 0
        self.recorder = None  # a gradient's run: the steps whose pass moved particles go to this (``watch``)

    def stats(self) -> dict:
        """At the last step: "iterations" (Jacobi iterations it ran), "before" and "after"
        (the largest l / l0 - 1 of a spring after the integrator's step and after the
        pass); of the steps so far: "unmet" (ended with a spring past the limit after
        ``ITERATIONS``), "undone" (unmet, and whose pass was undone: it left the worst
        spring worse than it found it), "steps" (whose pass moved particles) and "most"
        (the most iterations of one)."""
        iterations, before, after = self.last
        return {"iterations": iterations, "before": before, "after": after, "unmet": self.unmet,
                "undone": self.undone, "steps": self.steps, "most": self.most}

    def counters(self) -> dict:
        return {name: getattr(self, name) for name in ("last", "unmet", "steps", "most", "undone")}

    def end(self, state, t):
        """Limit ``state`` (after a step ending at time t, s)."""
        from massspring.kernels.strain_limit import strain_limit_iteration, strain_limit_restore, strain_limit_serial

        launches = ITERATIONS + 1  # the last only measures what the others left, unless it finds a spring over
        if self.serial:
            out = strain_limit_serial(self.dev, self.cfg, state, self.limit, TOLERANCE, self.dt, t, launches)
            k, first, worst = int(out[0]), float(out[1]), float(out[2])
        else:
            first = None
            for k in range(1, launches + 1):
                worst = strain_limit_iteration(self.dev, self.cfg, state, self.limit, TOLERANCE, self.dt, t,
                                               int(k == 1))
                first = worst if first is None else first
                if worst <= self.limit:
                    break
        undone = False
        if worst > self.limit:  # unmet: what the last launch left, measured (a limit of inf moves nothing)
            worst = strain_limit_iteration(self.dev, self.cfg, state, math.inf, TOLERANCE, self.dt, t, 0)
            if worst > first:
                strain_limit_restore(self.dev, state)
                worst, undone = first, True
                self.undone += 1
        self.unmet += worst > self.limit
        self.steps += k > 1
        self.most = max(self.most, k - 1)
        self.last = (k - 1, first, worst)
        if self.recorder is not None and first > self.limit and not undone:  # it moved particles
            self.recorder(state, t, self.dt)

    def watch(self, recorder):
        """From now on (a gradient's run: ``massspring.gradients``), a step whose pass moved
        particles (and was not undone) calls ``recorder(state, t, dt)`` at its end: the
        state it left, the time the step ended at and its size (s); the state it started
        from is in the bundle's ``x_sl_before``, ``v_sl_before``."""
        self.recorder = recorder

    def adjoint(self, sim, adj):
        """A gradient's record and run backwards of the steps this pass moved particles in
        (``backward.PassSteps``)."""
        from massspring.passes.strain_limit.backward import PassSteps

        return PassSteps(sim, adj, self)
