"""The adjoint of the linearised implicit step's self-collision pairs, with its pairs
frozen (``kernels/pair_penalty.py``).

A step of the linearised implicit integrator whose start positions x (n, 3) have pairs
of the mesh within the thickness t holds each as a penalty spring of Eq. 15: with its
particles ``idx`` (4,), signed weights w (4,) of its closest points at x (g = sum_k
w_k x_k, distance L = |g|, normal n = g / L) and the repulsion stiffness k (N/m),

    A += h^2 k (w w^T) (x) (n n^T),   b += h k (t - L) w (x) n   (rows of free particles).

The step's adjoint solve (``kernels/implicit_adjoint.py``) runs with these pairs
restored into the solve's fields (``SolvePairs``: the step's own, read as it began);
its multiplier mu (n, 3; zero at pins) then owes each pair's share of
d(mu . b - mu . A v')/d(x, k), v' the solve's velocity:

    phi = h^2 k (W mu . n)(W v' . n) - h k (t - L)(W mu . n),  W u = sum_k w_k u_k,

dL/dx -= d phi / dx (w, L, n through the closest points, solved on their region:
``self_collision_adjoint.regions``), dL/dk -= phi / k, and a pinned particle c's
velocity -= d phi / dv'_c (A's pin columns). d phi / dx is taken by complex steps of
phi, all pairs in one call (``self_collision_adjoint.complex_jacobian``).

The region of a pair's closest points comes from its weights: a point-triangle pair's
are (1, -b) with b >= 0, an edge-edge pair's (1 - s, s, -(1 - t), -t). They coincide
only for an edge-edge pair with s = 0 (its first edge's end against the other edge),
whose parametrization as a point against a triangle's edge (b = (0, 1 - t, t)) is the
same: ``kinds``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from massspring.passes.self_collision.adjoint import ReplayError, closest, complex_jacobian, regions

MATCH = 1e-9  # of the thickness: the closest points solved again on their region against the step's


@dataclass(frozen=True)
class SolvePairs:
    """The pairs of one step's solve (the fields of ``kernels/pair_penalty.py``):
    particles ``idx`` (P, 4) int32, weights ``w`` (P, 4), ``nf`` (P, 5) (normal,
    h^2 k, k (t - L)), each particle's first entry ``first`` (n + 1,) int32 and the
    entries ``entry`` (E,) int32 (pair x 4 + k)."""

    idx: np.ndarray
    w: np.ndarray
    nf: np.ndarray
    first: np.ndarray
    entry: np.ndarray

    @classmethod
    def read(cls, dev, n):
        """The solve's pairs as the device holds them (None if it holds none)."""
        from massspring.kernels.pair_penalty import pair_penalty_read

        count = int(dev.sp_count[0])
        if count == 0:
            return None
        entries = int(dev.sp_first[n])
        out = cls(np.empty((count, 4), np.int32), np.empty((count, 4)), np.empty((count, 5)),
                  np.empty(n + 1, np.int32), np.empty(entries, np.int32))
        pair_penalty_read(dev, out.idx, out.w, out.nf, out.first, out.entry)
        return out

    def write(self, dev):
        """Into the device's solve fields."""
        from massspring.kernels.pair_penalty import pair_penalty_write

        pair_penalty_write(dev, len(self.idx), len(self.entry), self.idx, self.w, self.nf, self.first, self.entry)

    @staticmethod
    def clear(dev, n):
        """No pairs in the device's solve fields."""
        from massspring.kernels.pair_penalty import pair_penalty_write

        pair_penalty_write(dev, 0, 0, np.zeros((1, 4), np.int32), np.zeros((1, 4)), np.zeros((1, 5)),
                           np.zeros(n + 1, np.int32), np.zeros(1, np.int32))


def kinds(w):
    """Each pair's kind (P,) from its weights (P, 4): -1 (point-triangle) where w = (1,
    -b) with b >= 0, else 1 (edge-edge); module docstring."""
    point = (w[:, 0] == 1.0) & np.all(w[:, 1:] <= 0.0, axis=1)
    return np.where(point, -1, 1)


def penalty_product(x, k, v, mu, free, w0, e, h, thickness):
    """phi (P,) of the module docstring: ``x`` (P, 4, 3) the pairs' start positions, ``k``
    (P,) N/m, ``v`` (P, 4, 3) their solved velocities, ``mu`` (P, 4, 3) the adjoint
    solve's multipliers, ``free`` (P, 4) bool, region ``w0``, ``e``; real or complex."""
    w, _, length, normal = closest(x, w0, e)
    pulled = along(np.where(free, w, 0.0), mu, normal)
    return h * h * k * pulled * along(w, v, normal) - h * k * (thickness - length) * pulled


def along(w, u, normal):
    """W u . n (P,): each pair's weighted sum of ``u`` (P, 4, 3) by ``w`` (P, 4), along its
    ``normal`` (P, 3)."""
    return np.sum(np.einsum("pk,pkc->pc", w, u) * normal, axis=1)


def penalty_adjoint(pairs, x, v, mu, free, h, thickness, k):
    """The pairs' shares (module docstring) at the step's start positions ``x``, solved
    velocities ``v`` and multipliers ``mu`` (n, 3), ``free`` (n,) bool: (dL/dx to add
    (n, 3), dL/dk to add, dL/d(a pinned particle's velocity) to add (n, 3))."""
    order = np.lexsort(pairs.idx.T[::-1])  # by their particles (the solve's order depends on the threads')
    idx, stored, nf = pairs.idx[order], pairs.w[order], pairs.nf[order]
    w0, e = regions(stored, kinds(stored))
    starts = x[idx]
    w, _, length, normal = closest(starts, w0, e)
    error = max(np.max(np.abs(w - stored)) * thickness, np.max(np.abs(normal - nf[:, :3])) * thickness,
                np.max(np.abs(k * (thickness - length) - nf[:, 4])) / k)
    if not error <= MATCH * thickness:
        raise ReplayError(why=f"a pair of the implicit solve solved again differs from the solve's by {error:.3g} m")
    pair_free = free[idx]
    fixed = (v[idx], mu[idx], pair_free, w0, e, h, thickness)
    jac = complex_jacobian(penalty_product, (starts, np.full(len(idx), float(k))), fixed)
    gx = np.zeros_like(x)
    np.add.at(gx, idx, -jac[:, :12].reshape(-1, 4, 3))
    gk = -float(jac[:, 12].sum())
    pulled = along(np.where(pair_free, w, 0.0), mu[idx], normal)
    column = h * h * k * pulled[:, None, None] * w[..., None] * normal[:, None, :]  # d phi / dv' per particle
    gpin = np.zeros_like(x)
    np.add.at(gpin, idx, np.where(pair_free[..., None], 0.0, -column))
    return gx, gk, gpin
