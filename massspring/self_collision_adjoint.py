"""The adjoint of the self-collision pass's repulsion, with its active set frozen.

Step 2 of the pass (``kernels/self_collision.py``) turns the state an integrator's step
left, positions x and velocities v (n, 3), into x', v' given the step's start positions
x0 (n, 3), the masses (n,) and dt = h (s). For each listed pair of particles ``idx``
(4,) with signed weights w (4,) of its closest points at x0 (sum_k w_k x0_k = g, its
distance L = |g|, normal n = g / L) closer than the thickness:

    r = sum_k w_k (x_k - x0_k) / h, vn = r . n, s = sum_k w_k^2 / m_k (free k),
    dvn = min(0.1 (thickness - L) / h - vn, max(-vn, 0) + h k_r (thickness - L) s),
    t = r - vn n, c = dvn n - min(mu dvn, |t|) t / |t|, dv_k = w_k c / (s m_k) (free k),

k_r the repulsion stiffness; each particle's dv are averaged over the pairs that touch
it (du), then x' = x + h du, v' = v + du, each coordinate clipped to the particle's
path box grown by thickness / 2 (v' changed with x'). The weights are the closest points'
on the region of the two primitives where they lie (a triangle's face, edge or corner;
each edge's inside or end), where they are smooth functions of x0: the least-squares
solution over the region's free parameters.

Frozen active set: which pairs repel, the min and max above, sticking or sliding,
which coordinates are clipped, and each closest point's region are those of the step
as taken; within them the pass is smooth and this is its exact Jacobian, transposed.
Where one of them switches, a derivative is not defined and none is claimed.

Each repelling pair's Jacobian of its four dv_k (12 values) in its 29 inputs (x0 and x of
its particles, their masses, k_r) is taken by complex-step differentiation of the
formulas above (f(z + i e) imaginary part / e with e = 1e-30: exact to round-off, no
difference quotient), vectorised over the pairs; the averaging and the clip are linear
and done by hand. Host arrays (numpy), a step at a time: ``Replay.backward``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from massspring.kernels.self_collision import SEPARATION

STEP = 1e-30  # the complex step
INPUTS = 29  # a pair's inputs: x0 (4 x 3), x (4 x 3), masses (4), the repulsion stiffness
REPLAY_TOLERANCE = 1e-9  # of the thickness (m) and the thickness a step (m/s): the replay against the pass


@dataclass(frozen=True)
class Record:
    """What the backward pass needs of a step in which the repulsion acted, besides the
    states before and after it: the step's candidate state ``x``, ``v`` (n, 3; before the
    pass) and the pass's listed pairs ``idx`` (P, 4) int, ``w`` (P, 4) (signed weights at
    x0), ``kind`` (P,) (1: edge-edge, -1: point-triangle)."""

    x: np.ndarray
    v: np.ndarray
    idx: np.ndarray
    w: np.ndarray
    kind: np.ndarray


class ReplayError(RuntimeError):
    """The repulsion replayed on the host does not give the pass's x', v' (by ``error`` m)."""

    def __init__(self, error):
        super().__init__(f"the self-collision pass replayed on the host differs from the pass by {error:.3g} m")
        self.error = float(error)


def regions(w, kind):
    """The closest points' regions from their weights ((P, 4), signed; ``kind`` (P,)):
    ``(w0, E)``, w = w0 + E theta with theta (P, 2) the free parameters (a column of E
    zero where there are fewer). A point-triangle pair's triangle weights b = -w[1:] are
    free on their support (b > 0): a face has two parameters, an edge one, a corner none;
    an edge-edge pair's s = w[1] and t = -w[3] are free strictly inside (0, 1)."""
    p = len(w)
    w0 = np.zeros((p, 4))
    e = np.zeros((p, 4, 2))
    edge = kind == 1
    # point-triangle: b = e_j0 + sum_c theta_c (e_jc - e_j0) on the support S = (j0, j1, j2)
    b = -w[:, 1:]
    support = b > 0
    order = np.argsort(~support, axis=1, kind="stable")
    count = support.sum(axis=1)
    rows = np.arange(p)
    w0[:, 0] = 1.0
    w0[rows, 1 + order[:, 0]] = -1.0
    for c in range(2):
        on = (count >= c + 2) & ~edge
        e[rows[on], 1 + order[on, 0], c] = 1.0
        e[rows[on], 1 + order[on, c + 1], c] = -1.0
    # edge-edge: (1 - s, s) = (1, 0) + s (-1, 1), (-(1 - t), -t) = (-1, 0) + t (1, -1)
    s, t = w[edge, 1], -w[edge, 3]
    free_s, free_t = (s > 0) & (s < 1), (t > 0) & (t < 1)
    w0[edge] = np.stack([np.where(free_s, 1.0, 1 - s), np.where(free_s, 0.0, s),
                         np.where(free_t, -1.0, t - 1), np.where(free_t, 0.0, -t)], axis=1)
    e[edge] = 0.0
    e[edge, 0, 0], e[edge, 1, 0] = -1.0 * free_s, 1.0 * free_s
    e[edge, 2, 1], e[edge, 3, 1] = 1.0 * free_t, -1.0 * free_t
    return w0, e


def pair_changes(x0, x, masses, free, w0, e, k_r, h, thickness, mu, branches=None):
    """Each pair's velocity changes dv (P, 4, 3) by the module docstring's formulas:
    ``x0``, ``x`` (P, 4, 3) and ``masses`` (P, 4) of its particles, ``free`` (P, 4) bool,
    region ``w0``, ``e`` (``regions``), ``k_r`` (P,) N/m; real or complex inputs.
    ``branches``: the frozen choices (from a real evaluation, which returns them as
    ``(dv, branches)``); the pairs that do not act get dv = 0."""
    a = np.einsum("pk,pkc->pc", w0, x0)
    bmat = np.einsum("pkj,pkc->pcj", e, x0)
    gram = np.einsum("pcj,pcl->pjl", bmat, bmat) + np.eye(2) * (~e.any(axis=1))[:, None, :]
    theta = np.linalg.solve(gram, -np.einsum("pcj,pc->pj", bmat, a)[..., None])[..., 0]
    w = w0 + np.einsum("pkj,pj->pk", e, theta)
    g = a + np.einsum("pcj,pj->pc", bmat, theta)
    length = np.sqrt(np.sum(g * g, axis=1))
    safe = np.where(length.real > 0, length, 1.0)
    normal = g / safe[:, None]
    rel = np.einsum("pk,pkc->pc", w, x - x0) / h
    inverse = np.sum(np.where(free, w * w / masses, 0.0), axis=1)
    vn = np.sum(rel * normal, axis=1)
    gap = thickness - length
    need = SEPARATION * gap / h - vn
    if branches is None:
        approach = vn.real < 0
        cap = np.where(approach, -vn, 0.0) + h * k_r * gap * inverse
        use_need = need.real <= cap.real
        dvn = np.where(use_need, need, cap)
    else:
        approach, use_need = branches["approach"], branches["need"]
        cap = np.where(approach, -vn, 0.0) + h * k_r * gap * inverse
        dvn = np.where(use_need, need, cap)
    tangent = rel - vn[:, None] * normal
    vt = np.sqrt(np.sum(tangent * tangent, axis=1))
    if branches is None:
        act = (length.real < thickness) & (length.real > 0) & (inverse.real > 0) & (dvn.real > 0)
        moving = vt.real > 0
        sliding = mu * dvn.real < vt.real
        branches = {"approach": approach, "need": use_need, "act": act, "moving": moving, "sliding": sliding}
        real = True
    else:
        act, moving, sliding = branches["act"], branches["moving"], branches["sliding"]
        real = False
    safe_vt = np.where(moving, vt, 1.0)
    coefficient = np.where(moving, np.where(sliding, mu * dvn / safe_vt, 1.0), 0.0)
    change = dvn[:, None] * normal - coefficient[:, None] * tangent
    impulse = change / np.where(act, inverse, 1.0)[:, None]
    dv = np.where((free & act[:, None])[..., None], w[..., None] * impulse[:, None, :] / masses[..., None], 0.0)
    return (dv, branches) if real else dv


class Replay:
    """The repulsion of one model's pass: ``masses`` (n,) kg, ``free`` (n,) bool (not
    pinned), dt ``h`` (s), ``thickness`` (m), friction ``mu``, repulsion stiffness
    ``k_r`` (N/m), in the device's particle numbering."""

    def __init__(self, masses, free, h, thickness, mu, k_r):
        self.masses, self.free = np.asarray(masses, dtype=np.float64), np.asarray(free, dtype=bool)
        self.h, self.thickness, self.mu, self.k_r = float(h), float(thickness), float(mu), float(k_r)

    def _pairs(self, record, x0):
        idx = record.idx
        w0, e = regions(record.w, record.kind)
        args = (x0[idx], record.x[idx], self.masses[idx], self.free[idx], w0, e, np.full(len(idx), self.k_r))
        return args, pair_changes(*args, self.h, self.thickness, self.mu)

    def forward(self, record, x0):
        """The repulsion of ``record``'s step from start positions ``x0`` (n, 3), replayed:
        ``(x', v', parts)``, ``parts`` what ``backward`` needs of it."""
        n, h, half = len(x0), self.h, 0.5 * self.thickness
        args, (dv, branches) = self._pairs(record, x0)
        counted = self.free[record.idx] & branches["act"][:, None]
        hits = np.bincount(record.idx[counted], minlength=n).astype(np.float64)
        touched = (hits > 0) & self.free
        du = np.zeros((n, 3))
        np.add.at(du, record.idx[counted], dv[counted])
        du[touched] /= hits[touched, None]
        x1 = np.where(touched[:, None], record.x + h * du, record.x)
        v1 = np.where(touched[:, None], record.v + du, record.v)
        low = np.minimum(x0, record.x) - half
        high = np.maximum(x0, record.x) + half
        below, above = touched[:, None] & (x1 < low), touched[:, None] & (x1 > high)
        x2 = np.where(below, low, np.where(above, high, x1))
        v2 = v1 + (x2 - x1) / h
        from_start = np.where(below, x0 < record.x, x0 > record.x)
        parts = dict(args=args, branches=branches, counted=counted, hits=hits, touched=touched, clipped=below | above,
                     from_start=from_start)
        return x2, v2, parts

    def backward(self, record, x0, after_x, after_v, lx, lv):
        """dL/d(x, v) of the step's candidate state, dL/dx0, dL/d(masses) (n,) and
        dL/dk_r from dL/d(x', v') ``lx``, ``lv`` (n, 3) of the state after the pass, at
        ``x0`` (the step's start positions) with the pass's own ``after_x``, ``after_v``
        (n, 3), which the replay must give (``ReplayError`` if not)."""
        n, h, idx = len(x0), self.h, record.idx
        x2, v2, parts = self.forward(record, x0)
        error = max(np.max(np.abs(x2 - after_x), initial=0.0), h * np.max(np.abs(v2 - after_v), initial=0.0))
        if not error <= REPLAY_TOLERANCE * self.thickness:
            raise ReplayError(error)
        clipped, from_start, counted, hits = parts["clipped"], parts["from_start"], parts["counted"], parts["hits"]
        gx = np.where(clipped, -lv / h, lx)  # through x', v' directly (a clipped x' is its bound)
        gv = lv.copy()
        bound = np.where(clipped, lx + lv / h, 0.0)  # dL/d(the bound a clipped coordinate took)
        gx0 = np.where(from_start, bound, 0.0)
        gx += np.where(from_start, 0.0, bound)
        gdu = np.where(parts["touched"][:, None] & ~clipped, h * lx + lv, 0.0) / np.maximum(hits, 1.0)[:, None]
        gm = np.zeros(n)
        gk = 0.0
        acting = np.flatnonzero(parts["branches"]["act"])
        if acting.size:
            jac = self._jacobian([arg[acting] for arg in parts["args"]],
                                 {key: b[acting] for key, b in parts["branches"].items()})
            gdv = np.where(counted[acting][..., None], gdu[idx[acting]], 0.0).reshape(len(acting), 12)
            grad = np.einsum("po,poi->pi", gdv, jac)
            np.add.at(gx0, idx[acting], grad[:, :12].reshape(-1, 4, 3))
            np.add.at(gx, idx[acting], grad[:, 12:24].reshape(-1, 4, 3))
            np.add.at(gm, idx[acting], grad[:, 24:28])
            gk = float(grad[:, 28].sum())
        return gx, gv, gx0, gm, gk

    def _jacobian(self, args, branches):
        """(P, 12, 29): d(dv) / d(x0, x, masses, k_r) of each pair, by complex steps."""
        x0, x, masses, free, w0, e, k_r = args
        p = len(x0)
        flat = np.concatenate([x0.reshape(p, 12), x.reshape(p, 12), masses, k_r[:, None]], axis=1)
        jac = np.empty((p, 12, INPUTS))
        for j in range(INPUTS):
            z = flat.astype(np.complex128)
            z[:, j] += 1j * STEP
            dv = pair_changes(z[:, :12].reshape(p, 4, 3), z[:, 12:24].reshape(p, 4, 3), z[:, 24:28], free, w0, e,
                              z[:, 28], self.h, self.thickness, self.mu, branches)
            jac[:, :, j] = dv.reshape(p, 12).imag / STEP
        return jac
