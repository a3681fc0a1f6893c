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

__all__ = ["PRECONDITIONERS", "Preconditioner", "SolverStats", "solve"]
