"""Symplectic (semi-implicit) Euler."""

from __future__ import annotations

import math

from massspring.defaults import FALLBACK_DT

from .explicit import ExplicitEuler


class SymplecticEuler(ExplicitEuler):
    """v' = v + dt f(x, v) / m, then x' = x + dt v': the explicit step with the new
    velocity in the position update. First order; stable for dt < 2 / omega_max undamped."""

    name = "symplectic"
    order = 1
    description = "symplectic Euler: v' = v + dt f(x, v)/m, x' = x + dt v'"
    symplectic = True
    ladder = ("symplectic_dt", (0.5, 0.9, 1.1, 1.5, 3.0))

    @staticmethod
    def suggest_dt(prediction):
        """Half the predicted stability limit."""
        limit = prediction.symplectic_dt
        return 0.5 * limit if math.isfinite(limit) else FALLBACK_DT
