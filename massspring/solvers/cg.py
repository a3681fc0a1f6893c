"""The CG driver of Eq. 15: preconditioned conjugate gradient from the warm start v_n.

Contract (as ``scipy.sparse.linalg.cg``, stated for this solver): solve
A v = b with relative tolerance ``tol`` on the *true* residual ||b - A v|| / ||b - A v_0||
on the free directions, relative to the first residual of the warm start v_0 (for
Eq. 15 the right-hand side of its velocity-change form, h (f + h K v_n)), or down to
``ROUNDOFF`` eps ||b|| where that is larger (a steady state's first residual is
round-off),
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

import taichi as ti

from massspring.kernels import cg, operator

ROUNDOFF = 100  # a residual below ROUNDOFF eps ||S b|| is round-off: solved, whatever tol asks
EPS64, EPS32 = 2.0**-52, 2.0**-23


@dataclass(frozen=True)
class SolverStats:
    """Outcome of one implicit step's solve.

    iterations: CG iterations (all Newton iterations' together); residual: CG's true
    relative residual ||b - A v|| / ||b - A v_0|| recomputed at exit (its last solve's);
    converged: the step met its tolerances (CG's, and Newton's for a Newton-solved
    integrator); reason: why it stopped ("converged", "max_iter", "indefinite" when
    p.Ap <= 0, "stalled" when a restart from the true residual no longer reduces it,
    as f32 round-off can cause, "non-finite" when the right-hand side or the residual
    overflowed); setup_s: seconds of the preconditioner's per-step setup (0 for
    pointwise ones, set up in the operator's refresh); first_residual: ||S (b - A v_0)||
    at the warm start of the step's first solve (kg m/s), what CG's tolerance is
    relative to.

    Newton-solved integrators (``integrators/newton.py``) also give: newton_iterations
    (linear solves), cg_per_newton (CG iterations of each), cuts (line-search halvings
    in all), newton_residuals (||g|| of the implicit equations at each iterate,
    relative to its value at the warm start: 1.0 first) and newton_residual (the
    last of them); None / () / 0 for the linearised step. Their reason "max_newton":
    the Newton iteration limit came first.
    """

    iterations: int
    residual: float
    converged: bool
    reason: str
    setup_s: float = 0.0
    newton_iterations: int | None = None
    cg_per_newton: tuple = ()
    cuts: int = 0
    newton_residual: float | None = None
    newton_residuals: tuple = ()
    first_residual: float = math.nan


def solve(dev, cfg, preconditioner, dt, tol, max_iter, serial, t=0.0, x=None, mode=operator.LINEARISED) -> SolverStats:
    """Refresh the operator at the state (``x``, default ``dev.x``; ``dev.v``) at simulated
    time ``t`` (s: where moving colliders are) in ``mode`` (``kernels.operator``; none for
    ``REFRESHED``: the caller did), then solve A v = b in ``dev.v`` from the iterate it holds."""
    x = dev.x if x is None else x
    floor = ROUNDOFF * (EPS32 if cfg.real == ti.f32 else EPS64)
    setup_s = 0.0
    if serial and preconditioner.kernel is not None:
        iterations, residual, reason, first = cg.cg_solve(dev, cfg, x, dt, t, tol, floor, max_iter, mode)
        iterations, residual, reason = int(iterations), float(residual), int(reason)
    else:
        if mode != operator.REFRESHED:
            cg.cg_refresh(dev, cfg, x, dt, t, mode)
        start = time.perf_counter()
        preconditioner.setup(dt)
        setup_s = time.perf_counter() - start
        iterations, residual, reason, first = _parallel(dev, cfg, preconditioner, tol, floor, max_iter)
    return SolverStats(iterations, residual, reason == cg.CONVERGED, cg.REASONS[reason], setup_s,
                       first_residual=float(first))


def _restart(dev, cfg, preconditioner):
    """r = b - A v and p = z = P r; returns (r.z, r.r, b.b)."""
    rz, rr, bb = cg.cg_begin(dev, cfg)
    if math.isfinite(bb) and bb > 0:
        rz = _global_direction(dev, cfg, preconditioner, rz)
    return rz, rr, bb


def _global_direction(dev, cfg, preconditioner, rz):
    """After ``cg_begin``: p = z = P r for a global preconditioner (a pointwise one's
    ``cg_begin`` did it); returns r.z."""
    if preconditioner.kernel is None:
        rz = preconditioner.apply()
        cg.cg_direction(dev, cfg, 0.0)
    return rz


def _parallel(dev, cfg, preconditioner, tol, floor, max_iter):
    """PCG with one kernel launch per phase; the loop of ``kernels.cg.serial_solve``."""
    pointwise = preconditioner.kernel is not None
    rz, rr, bb = _restart(dev, cfg, preconditioner)
    if not math.isfinite(bb):
        return 0, math.inf, cg.NONFINITE, math.inf
    tol = max(tol, floor * math.sqrt(bb / rr)) if rr > 0 else tol  # a residual at b's round-off is solved
    bb = rr  # the tolerance is relative to the first residual
    if bb == 0.0:  # the iterate solves the system exactly
        return 0, 0.0, cg.CONVERGED, 0.0
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
            rz, rr, _ = cg.cg_begin(dev, cfg)  # the true residual; P r only if CG goes on
        residual = math.sqrt(max(rr, 0.0) / bb) if math.isfinite(rr) else math.inf
        done, reason, best = cg.exit_rule(math.isfinite(residual), iterations, cycle, residual, tol, best,
                                          reason, max_iter)
        if not done:
            rz = _global_direction(dev, cfg, preconditioner, rz)
    return iterations, residual, reason, math.sqrt(bb)
