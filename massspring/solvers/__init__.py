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
from .multigrid_f32 import MultigridF32
from .none import NoPreconditioner

PRECONDITIONERS = {cls.name: cls for cls in (BlockJacobi, Multigrid, MultigridF32, NoPreconditioner)}
CHOICES = ("auto", *PRECONDITIONERS)  # what the API, scene files and the CLI accept

# "auto" picks multigrid from this many free particles on, block-Jacobi below: between
# the crossovers of the step time at ks 1e6 and ks 1e4 that benchmarks/scaling.py
# measures (cloth, dt 1/60, f64; benchmarks/results/scaling_crossover.json and docs/performance.md).
MULTIGRID_FROM = 5_000


def resolve(name, model, finest_f32=False) -> str:
    """The preconditioner ``name`` stands for on ``model`` (``resolve_for_count``)."""
    return resolve_for_count(name, int(model.free_mask().sum()), finest_f32)


def resolve_for_count(name, free_particles, finest_f32=False) -> str:
    """What ``name`` stands for on a model of ``free_particles``: itself, or for "auto"
    block-Jacobi below ``MULTIGRID_FROM`` free particles and multigrid from there, with
    its finest level in f32 (``multigrid-f32``) where the integrator gains by it
    (``finest_f32``: ``Integrator.finest_f32``)."""
    if name != "auto":
        return name
    if free_particles < MULTIGRID_FROM:
        return "block-jacobi"
    return "multigrid-f32" if finest_f32 else "multigrid"


__all__ = ["CHOICES", "MULTIGRID_FROM", "PRECONDITIONERS", "Preconditioner", "SolverStats", "resolve", "resolve_for_count", "solve"]
