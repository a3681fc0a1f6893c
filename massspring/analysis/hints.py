"""What the stability ladder and the study do with each integrator: one ``Hints`` record
per integrator name (``HINTS``), read through ``hints``.

These are analysis's, not the integrators' (whose capabilities are their ``Traits``):
the rows of the stability ladder (``stability.LADDER``, ``massspring stability``) and
the tolerance the work-precision study sweeps (``study.run_study``, ``massspring
study``). A new integrator adds its row here if it wants to be on the ladder or to
have a tolerance swept by the study; without a row it gets ``NO_HINTS`` (no ladder
rows, no sweep: one line per preconditioner, at its default tolerances).
"""

from __future__ import annotations

from dataclasses import dataclass

from massspring.integrators import INTEGRATORS


@dataclass(frozen=True)
class Hints:
    """``ladder``: its rows of the stability ladder, (the ``stability.Prediction``
    attribute its dt is relative to, the multiples of it), None: none.
    ``ladder_without_fix``: also run the ladder without the definiteness fix.
    ``swept``: the option the study sweeps (a tolerance: its ``Option.sweep``), None: none."""

    ladder: tuple | None = None
    ladder_without_fix: bool = False
    swept: str | None = None


NO_HINTS = Hints()
NEWTON_HINTS = Hints(ladder=("symplectic_dt", (1.0, 10.0, 100.0, 1000.0)), swept="newton_tol")

# By registry name (``integrators.INTEGRATORS``); rk4 has none (the study's reference).
HINTS = {
    "explicit": Hints(ladder=("explicit_doubling_dt", (0.5, 1.0, 2.0, 10.0, 100.0))),
    "symplectic": Hints(ladder=("symplectic_dt", (0.5, 0.9, 1.1, 1.5, 3.0))),
    "implicit": Hints(ladder=("symplectic_dt", (1.0, 10.0, 100.0, 1000.0)), ladder_without_fix=True, swept="cg_tol"),
    "backward-euler": NEWTON_HINTS,
    "bdf2": NEWTON_HINTS,
    "midpoint": NEWTON_HINTS,
}


def hints(integrator: str) -> Hints:
    """The ``Hints`` of the integrator named ``integrator``: its row of ``HINTS``, else
    ``NO_HINTS``. ValueError for a name that is not in ``INTEGRATORS``."""
    if integrator not in INTEGRATORS:
        raise ValueError(f"integrator: unknown value {integrator!r}, expected one of {', '.join(INTEGRATORS)}")
    return HINTS.get(integrator, NO_HINTS)
