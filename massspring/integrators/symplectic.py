"""Symplectic (semi-implicit) Euler."""

from __future__ import annotations

from .explicit import ExplicitEuler


class SymplecticEuler(ExplicitEuler):
    """v' = v + dt f(x, v) / m, then x' = x + dt v': the explicit step with the new
    velocity in the position update. First order; stable for dt < 2 / omega_max undamped."""

    name = "symplectic"
    order = 1
    description = "symplectic Euler: v' = v + dt f(x, v)/m, x' = x + dt v'"
    symplectic = True
    ladder = ("symplectic_dt", (0.5, 0.9, 1.1, 1.5, 3.0))
    grows_undamped = False
    limit_reference = True

    @staticmethod
    def stability_limit(prediction):
        """The predicted stability limit."""
        return prediction.symplectic_dt
