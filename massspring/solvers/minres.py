"""Preconditioned MINRES on host vectors, for symmetric systems that may be indefinite:
a Newton-solved step's adjoint J mu = dL/du with the residual's true Jacobian J
(``integrators/newton.py``), preconditioned by the run's own preconditioner of the
definiteness-fixed operator (symmetric positive definite).

The method of Paige and Saunders (1975): the Lanczos process in the preconditioner's
inner product, with the tridiagonal least-squares problem solved by Givens rotations as
it grows, so that each iteration takes one product with A, one with the preconditioner
B and a few vectors of memory, and the iterate minimises ||b - A x|| in B's norm over
the Krylov space (no restarts: short recurrences). Plain numpy, deterministic: every
inner product is numpy's pairwise sum, not a BLAS call whose order may depend on the
thread count. SciPy's ``minres`` does the same but is not a dependency of the core
package.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class MinresResult:
    """``x``: the iterate; ``iterations``: products with A (one a Lanczos step);
    ``residual``: the true residual ||b - A x||_B in the preconditioner's norm at exit,
    relative to that of the start; ``reason``: "converged", "max_iter", "stalled" (a
    restart from the true residual did not halve it), "indefinite" (the preconditioner
    gave r . B r <= 0) or "non-finite"."""

    x: np.ndarray
    iterations: int
    residual: float
    reason: str

    @property
    def converged(self) -> bool:
        return self.reason == "converged"


def _dot(a, b) -> float:
    return float(np.sum(a * b))


def minres(matvec, precondition, b, x0, tol, max_iter, floor=0.0) -> MinresResult:
    """Solve A x = b from ``x0`` (float64 arrays of any one shape), A symmetric (``matvec``(v)
    = A v), preconditioned by the symmetric positive definite B (``precondition``(r) =
    B r), until the true residual's B-norm is at most ``tol`` times the start's (or
    ``floor`` times ||b||_B: round-off of b), in at most ``max_iter`` products with A.

    The estimate the recurrences give is checked at exit against the true residual; where
    that misses, the process starts again from the iterate, and stops "stalled" when a
    restart did not halve it.
    """
    x = np.array(x0, dtype=np.float64)
    bz = precondition(b)
    b_norm = math.sqrt(max(_dot(b, bz), 0.0))
    first = best = None
    iterations = 0
    while True:
        r = b - matvec(x)
        z = precondition(r)
        rz = _dot(r, z)
        if not math.isfinite(rz):
            return MinresResult(x, iterations, math.inf, "non-finite")
        if rz < 0:
            return MinresResult(x, iterations, math.inf, "indefinite")
        norm = math.sqrt(rz)
        if first is None:
            first = norm
            if first == 0.0:
                return MinresResult(x, iterations, 0.0, "converged")
            goal = max(tol, floor * b_norm / first)
        residual = norm / first
        if residual <= goal:
            return MinresResult(x, iterations, residual, "converged")
        if best is not None and residual > 0.5 * best:
            return MinresResult(x, iterations, residual, "stalled")
        if iterations >= max_iter:
            return MinresResult(x, iterations, residual, "max_iter")
        best = residual
        x, iterations, reason = _lanczos(matvec, precondition, x, r, z, norm, goal * first, iterations, max_iter)
        if reason is not None:
            return MinresResult(x, iterations, math.inf, reason)


def _lanczos(matvec, precondition, x, r, z, beta, target, iterations, max_iter):
    """MINRES's iterations from ``x`` with residual ``r``, B r = ``z``, beta = sqrt(r . z),
    until the estimated residual norm is at most ``target`` or ``max_iter`` products in
    all. Returns (x, products so far, None or the reason it broke down)."""
    previous_r, r_now = np.zeros_like(r), r
    w, w_before = np.zeros_like(r), np.zeros_like(r)
    beta_before = 0.0
    cos, sin = -1.0, 0.0
    phi_bar = beta
    d_bar = epsilon = 0.0
    while iterations < max_iter:
        v = z / beta
        y = matvec(v)
        iterations += 1
        if beta_before > 0:
            y = y - (beta / beta_before) * previous_r
        alpha = _dot(v, y)
        y = y - (alpha / beta) * r_now
        previous_r, r_now = r_now, y
        z = precondition(y)
        rz = _dot(y, z)
        if not math.isfinite(rz):
            return x, iterations, "non-finite"
        if rz < 0:
            return x, iterations, "indefinite"
        beta_before, beta = beta, math.sqrt(rz)
        # the new column of the tridiagonal matrix through the rotations so far
        epsilon_before = epsilon
        delta = cos * d_bar + sin * alpha
        gamma_bar = sin * d_bar - cos * alpha
        epsilon = sin * beta
        d_bar = -cos * beta
        gamma = math.hypot(gamma_bar, beta)
        if gamma == 0.0:  # A v = 0 on the Krylov space: x cannot move further
            return x, iterations, None
        cos, sin = gamma_bar / gamma, beta / gamma
        phi = cos * phi_bar
        phi_bar = sin * phi_bar
        w_before, w = w, (v - epsilon_before * w_before - delta * w) / gamma
        x = x + phi * w
        if phi_bar <= target or beta == 0.0:
            break
    return x, iterations, None
