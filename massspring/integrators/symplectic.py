"""Symplectic (semi-implicit) Euler."""

from __future__ import annotations

import dataclasses

from .explicit import ExplicitEuler


class SymplecticEuler(ExplicitEuler):
    """v' = v + dt f(x, v) / m, then x' = x + dt v': the explicit step with the new
    velocity in the position update. First order; stable for dt < 2 / omega_max undamped."""

    name = "symplectic"
    description = "symplectic Euler: v' = v + dt f(x, v)/m, x' = x + dt v'"
    traits = dataclasses.replace(ExplicitEuler.traits, order=1, grows_undamped=False, limit_reference=True)
    symplectic = True

    @staticmethod
    def stability_limit(prediction):
        """The predicted stability limit."""
        return prediction.symplectic_dt
