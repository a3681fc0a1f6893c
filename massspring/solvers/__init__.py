"""Linear solvers of Eq. 15: the CG driver and its preconditioners.

A preconditioner is a subclass of :class:`base.Preconditioner`, registered in
``PRECONDITIONERS`` under its name; the CG driver (``cg.solve``) does not know
which one it has. Adding one means a module here (with its kernels in
``kernels/``) and an entry below.
"""

from .base import Preconditioner
from .block_jacobi import BlockJacobi
from .cg import SolverStats, solve
from .multigrid import Multigrid
from .none import NoPreconditioner

PRECONDITIONERS = {cls.name: cls for cls in (BlockJacobi, Multigrid, NoPreconditioner)}
CHOICES = ("auto", *PRECONDITIONERS)  # what the API, scene files and the CLI accept

# "auto" picks multigrid from this many free particles on, block-Jacobi below: between
# the crossovers of the step time at ks 1e6 and ks 1e4 that benchmarks/scaling.py
# measures (cloth, dt 1/60, f64; benchmarks/results/scaling_crossover.json and docs/performance.md).
MULTIGRID_FROM = 5_000


def resolve(name, model) -> str:
    """The preconditioner ``name`` stands for on ``model``: itself, or for "auto"
    multigrid from ``MULTIGRID_FROM`` free particles on, else block-Jacobi."""
    return resolve_for_count(name, int(model.free_mask().sum()))


def resolve_for_count(name, free_particles) -> str:
    """``resolve`` for a model of ``free_particles`` not yet built."""
    if name != "auto":
        return name
    return "multigrid" if free_particles >= MULTIGRID_FROM else "block-jacobi"


__all__ = ["CHOICES", "MULTIGRID_FROM", "PRECONDITIONERS", "Preconditioner", "SolverStats", "resolve", "resolve_for_count", "solve"]
