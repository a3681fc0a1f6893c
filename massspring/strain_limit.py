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

import numpy as np

ITERATIONS = 500  # at most this many Jacobi iterations a step
TOLERANCE = 1e-4  # violated springs are shortened to limit - this (l / l0 - 1); the pass ends with none past the limit
PASS_BYTES_PER_SPRING = 24  # sl_dx, a vec3 per spring (f64); sl_k is 4 bytes a particle


def check(value, n_springs):
    """``Model``'s ``strain_limit``: None, or a finite number > 0 (the largest l / l0 - 1);
    ValueError naming ``strain_limit`` otherwise."""
    if value is None:
        return None
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"strain_limit: expected None or a number > 0 (the largest stretch l / l0 - 1), "
                         f"got {value!r}")
    value = float(value)
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"strain_limit: must be a finite number > 0 (the largest stretch l / l0 - 1), got {value!r}")
    if n_springs == 0:
        raise ValueError("strain_limit: the model has no springs to limit")
    return value


def declare(layout):
    """The pass's fields in ``layout`` (a ``device.Layout``): ``sl_dx`` (a vec3 per spring)
    and ``sl_k`` (an i32 per particle)."""
    import taichi as ti

    layout.vectors("sl_dx", layout.real, "spring")
    layout.add("sl_k", ti.i32, "particle")


class Pass:
    """The strain limit of one simulation, run on the state after each step (``end``;
    ``serial``: all its iterations in one serial launch, else one parallel launch each):
    Jacobi iterations until no spring is stretched past the limit, at most
    ``ITERATIONS`` that move particles (then one more launch measures, and moves them
    again if a spring is still over). ``last``: (iterations that moved particles, the
    largest l / l0 - 1 before the pass, the largest at the last launch's start) of the
    last step; ``unmet``: steps that ended with a spring still past the limit;
    ``steps``: steps whose pass moved particles; ``most``: the most iterations of a step.
    """

    def __init__(self, dev, cfg, limit, serial, dt):
        self.dev, self.cfg, self.limit, self.serial, self.dt = dev, cfg, limit, serial, dt
        self.last = (0, 0.0, 0.0)
        self.unmet = self.steps = self.most = 0

    def end(self, state, t):
        """Limit ``state`` (after a step ending at time t, s)."""
        from massspring.kernels.strain_limit import strain_limit_iteration, strain_limit_serial

        launches = ITERATIONS + 1  # the last only measures what the others left, unless it finds a spring over
        if self.serial:
            out = strain_limit_serial(self.dev, self.cfg, state, self.limit, TOLERANCE, self.dt, t, launches)
            k, first, worst = int(out[0]), float(out[1]), float(out[2])
        else:
            first = None
            for k in range(1, launches + 1):
                worst = strain_limit_iteration(self.dev, self.cfg, state, self.limit, TOLERANCE, self.dt, t)
                first = worst if first is None else first
                if worst <= self.limit:
                    break
        self.unmet += worst > self.limit
        self.steps += k > 1
        self.most = max(self.most, k - 1)
        self.last = (k - 1, first, worst)
