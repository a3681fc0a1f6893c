"""The CG driver of Eq. 15: preconditioned conjugate gradient from the warm start v_n.

Contract (as ``scipy.sparse.linalg.cg``, stated for this solver): solve
A v = b with relative tolerance ``tol`` on the *true* residual ||b - A v|| / ||b||
(on the free directions; relative to the first residual if b is 0 there),
recomputed at exit (the recursively updated residual drifts, in f32 especially);
if the true residual misses the tolerance, CG restarts from it, and stops as
"stalled" when a restart no longer halves it. At most ``max_iter`` iterations in
all. The outcome is a :class:`SolverStats`, never an exception.

Two drivers run the same kernels' arithmetic (``kernels/cg.py``): ``serial`` runs
the refresh and the whole solve in one launch (pointwise preconditioners only);
otherwise Python drives one kernel per CG phase.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

from massspring.kernels import cg


@dataclass(frozen=True)
class SolverStats:
    """Outcome of one implicit step's CG solve.

    iterations: CG iterations; residual: true relative residual ||b - A v|| / ||b||
    recomputed at exit; converged: residual <= tolerance; reason: why CG stopped
    ("converged", "max_iter", "indefinite" when p.Ap <= 0, "stalled" when a restart
    from the true residual no longer reduces it, as f32 round-off can cause,
    "non-finite" when the right-hand side or the residual overflowed); setup_s: seconds
    of the preconditioner's per-step setup (0 for pointwise ones, set up in the
    operator's refresh).
    """

    iterations: int
    residual: float
    converged: bool
    reason: str
    setup_s: float = 0.0


def solve(dev, cfg, preconditioner, dt, tol, max_iter, serial, t=0.0) -> SolverStats:
    """Refresh the operator at the bundle's state (at simulated time ``t``, s: where moving
    colliders are), then solve A v = b in ``dev.v``."""
    setup_s = 0.0
    if serial and preconditioner.kernel is not None:
        iterations, residual, reason = cg.cg_solve(dev, cfg, dt, t, tol, max_iter)
        iterations, residual, reason = int(iterations), float(residual), int(reason)
    else:
        cg.cg_refresh(dev, cfg, dt, t)
        start = time.perf_counter()
        preconditioner.setup(dt)
        setup_s = time.perf_counter() - start
        iterations, residual, reason = _parallel(dev, cfg, preconditioner, tol, max_iter)
    return SolverStats(iterations, residual, reason == cg.CONVERGED, cg.REASONS[reason], setup_s)


def _restart(dev, cfg, preconditioner):
    """r = b - A v and p = z = P r; returns (r.z, r.r, b.b)."""
    rz, rr, bb = cg.cg_begin(dev, cfg)
    if preconditioner.kernel is None and math.isfinite(bb) and bb > 0:
        rz = preconditioner.apply()
        cg.cg_direction(dev, cfg, 0.0)
    return rz, rr, bb


def _parallel(dev, cfg, preconditioner, tol, max_iter):
    """PCG with one kernel launch per phase; the loop of ``kernels.cg.cg_solve``."""
    pointwise = preconditioner.kernel is not None
    rz, rr, bb = _restart(dev, cfg, preconditioner)
    if not math.isfinite(bb):
        return 0, math.inf, cg.NONFINITE
    if bb == 0.0:  # b vanishes on the free directions: prescribed velocities drive the solve
        bb = rr
    if bb == 0.0:  # the iterate solves the system exactly
        return 0, 0.0, cg.CONVERGED
    target = tol * tol * bb
    iterations, reason, best, done = 0, cg.CONVERGED, 1e308, False
    residual = math.inf
    while not done:
        cycle = 0
        while rr > target and iterations < max_iter:
            pq = cg.cg_apply(dev, cfg)
            if not (math.isfinite(pq) and pq > 0.0) or rz == 0.0:
                reason = cg.INDEFINITE
                break
            rz_new, rr = cg.cg_update(dev, cfg, rz / pq)
            if not pointwise:
                rz_new = preconditioner.apply()
            iterations += 1
            cycle += 1
            cg.cg_direction(dev, cfg, rz_new / rz)
            rz = rz_new
        if cycle:
            rz, rr, _ = _restart(dev, cfg, preconditioner)
        residual = math.sqrt(max(rr, 0.0) / bb) if math.isfinite(rr) else math.inf
        done, reason, best = cg.exit_rule(math.isfinite(residual), iterations, cycle, residual, tol, best,
                                          reason, max_iter)
    return iterations, residual, reason
