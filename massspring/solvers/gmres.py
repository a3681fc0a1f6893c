"""Restarted GMRES on host vectors, for the few nonsymmetric systems whose operator is
itself a preconditioned solve (a Newton-solved step's adjoint with spring damping:
``integrators/newton.py``). Plain numpy, deterministic: every inner product is
numpy's pairwise sum, not a BLAS call whose order may depend on the thread count.
SciPy's ``gmres`` would do the same work but is not a dependency of the core package.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

RESTART = 40  # Krylov vectors kept before a restart (each as large as the solution: 24 n bytes)


@dataclass(frozen=True)
class GmresResult:
    """``x``: the iterate; ``products``: operator products taken; ``residual``: the last
    true residual relative to ||b||; ``converged``: whether it met the tolerance."""

    x: np.ndarray
    products: int
    residual: float
    converged: bool


def _dot(a, b) -> float:
    return float(np.sum(a * b))


def gmres(matvec, b, x0, tol, max_products, restart=RESTART) -> GmresResult:
    """Solve A x = b from ``x0`` (float64 arrays of any one shape) with ``matvec``(v) =
    A v, until ||b - A x|| <= ``tol`` ||b|| (the true residual, taken again at each
    restart) or ``max_products`` products of A."""
    x = np.array(x0, dtype=np.float64)
    scale = math.sqrt(_dot(b, b)) or 1.0
    products = 0
    while True:
        r = b - matvec(x)
        products += 1
        beta = math.sqrt(_dot(r, r))
        if beta <= tol * scale or products >= max_products or not math.isfinite(beta):
            return GmresResult(x, products, beta / scale, beta <= tol * scale)
        basis = [r / beta]
        h = np.zeros((restart + 1, restart))
        cs, sn = np.zeros(restart), np.zeros(restart)
        g = np.zeros(restart + 1)
        g[0] = beta
        k = 0
        for j in range(restart):
            w = matvec(basis[j])
            products += 1
            for i in range(j + 1):  # modified Gram-Schmidt
                h[i, j] = _dot(w, basis[i])
                w = w - h[i, j] * basis[i]
            h[j + 1, j] = math.sqrt(_dot(w, w))
            if h[j + 1, j] > 0:
                basis.append(w / h[j + 1, j])
            for i in range(j):  # the rotations so far, then this column's
                h[i, j], h[i + 1, j] = cs[i] * h[i, j] + sn[i] * h[i + 1, j], -sn[i] * h[i, j] + cs[i] * h[i + 1, j]
            norm = math.hypot(h[j, j], h[j + 1, j])
            cs[j], sn[j] = (h[j, j] / norm, h[j + 1, j] / norm) if norm > 0 else (1.0, 0.0)
            h[j, j], h[j + 1, j] = norm, 0.0
            g[j], g[j + 1] = cs[j] * g[j], -sn[j] * g[j]
            k = j + 1
            if abs(g[k]) <= tol * scale or products + 1 >= max_products or len(basis) == k:
                break
        y = np.zeros(k)
        for i in reversed(range(k)):  # H[:k, :k] y = g[:k], upper triangular
            y[i] = (g[i] - _dot(h[i, i + 1:k], y[i + 1:k])) / h[i, i] if h[i, i] != 0 else 0.0
        for i in range(k):
            x = x + y[i] * basis[i]
