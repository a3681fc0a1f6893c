"""Peer implementations the benchmarks run beside massspring, on the same systems.

* ``assemble_system``: Eq. 15 assembled as a SciPy sparse matrix on the free degrees
  of freedom (COO -> CSR), the way a sparse-matrix code does it every step.
* ``scipy_pcg`` / ``scipy_direct``: SciPy's Jacobi-preconditioned CG and a sparse
  LU (``factorized``) on that matrix.
* ``TaichiMatrixFreeCG``: Taichi's own ``ti.linalg.MatrixFreeCG`` with a
  ``LinearOperator`` whose matvec is a Taichi kernel (gather over springs).
* ``numpy_euler_step``: explicit / symplectic Euler vectorised with NumPy (bincount scatter).

Every iterative peer stops where massspring's CG does: at a residual ||b - A v|| of at
most ``tol`` times the first one, ||b - A v0|| with v0 = v_n (``first_residual``).

The numpy formulas here are written independently of kernels/ (same equations).
"""

import numpy as np

from massspring.device import adjacency

TINY = 1e-12


def spring_geometry(x, springs):
    d = x[springs[:, 1]] - x[springs[:, 0]]
    length = np.linalg.norm(d, axis=1)
    safe = length > TINY
    n = np.zeros_like(d)
    n[safe] = d[safe] / length[safe, None]
    return n, length, safe


def spring_forces(model, x, v, damping=True, gravity=True):
    """(n, 3) total force per particle (Eq. 1-3), scattered with bincount."""
    s = model.springs
    n, length, safe = spring_geometry(x, s)
    mag = np.where(safe, model.stiffness * (length - model.rest_lengths), 0.0)
    if damping:
        mag = mag + model.damping * np.einsum("ij,ij->i", v[s[:, 1]] - v[s[:, 0]], n)
    fs = mag[:, None] * n
    count = model.n_particles
    f = np.stack([np.bincount(s[:, 0], fs[:, k], count) - np.bincount(s[:, 1], fs[:, k], count)
                  for k in range(3)], axis=1)
    if gravity:
        f += model.masses[:, None] * model.gravity
    return f


def numpy_euler_step(model, x, v, dt, symplectic=False):
    """One explicit (Eq. 7-8) or symplectic Euler step with NumPy; fixed particles stay put."""
    a = spring_forces(model, x, v) / model.masses[:, None]
    v_new = v + dt * a
    v_new[model.fixed] = 0.0
    x_new = x + dt * (v_new if symplectic else v)
    return x_new, v_new


def assemble_system(model, x, v, dt, definiteness_fix=True):
    """Eq. 15 on the free DOFs: (A as scipy CSR, b, free particle indices)."""
    import scipy.sparse as sp

    s = model.springs
    n, length, safe = spring_geometry(x, s)
    c = np.where(safe, model.rest_lengths / np.where(safe, length, 1.0) - 1.0, 0.0)
    if definiteness_fix:
        c = np.minimum(c, 0.0)
    a = -dt * dt * model.stiffness * c
    b = dt * dt * model.stiffness * (1.0 + c) + dt * model.damping
    block = a[:, None, None] * np.eye(3) + b[:, None, None] * n[:, :, None] * n[:, None, :]

    free = model.free_mask()
    index = np.full(model.n_particles, -1)
    index[free] = np.arange(free.sum())
    nf = int(free.sum())
    rows, cols, vals = [], [], []
    k3 = np.arange(3)
    for p, q, sign in ((0, 0, 1.0), (1, 1, 1.0), (0, 1, -1.0), (1, 0, -1.0)):
        ip, iq = index[s[:, p]], index[s[:, q]]
        keep = (ip >= 0) & (iq >= 0)
        r = 3 * ip[keep, None, None] + k3[None, :, None]
        col = 3 * iq[keep, None, None] + k3[None, None, :]
        rows.append(np.broadcast_to(r, (keep.sum(), 3, 3)).ravel())
        cols.append(np.broadcast_to(col, (keep.sum(), 3, 3)).ravel())
        vals.append(sign * block[keep].ravel())
    diag = np.repeat(model.masses[free], 3)
    rows.append(np.arange(3 * nf))
    cols.append(np.arange(3 * nf))
    vals.append(diag)
    matrix = sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                           shape=(3 * nf, 3 * nf)).tocsr()
    f = spring_forces(model, x, v, damping=False)
    rhs = (model.masses[:, None] * v + dt * f)[free].ravel()
    return matrix, rhs, np.flatnonzero(free)


def first_residual(matrix, rhs, x0):
    """||rhs - matrix x0||: what a CG tolerance is relative to, as in massspring."""
    return float(np.linalg.norm(rhs - matrix @ x0))


def scipy_pcg(matrix, rhs, x0, tol):
    """SciPy CG with a Jacobi preconditioner, to ``tol`` times the first residual;
    returns (solution, iterations)."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import cg

    count = [0]

    def callback(_):
        count[0] += 1

    jacobi = sp.diags(1.0 / matrix.diagonal())
    sol, info = cg(matrix, rhs, x0=x0, rtol=0.0, atol=tol * first_residual(matrix, rhs, x0), M=jacobi,
                   maxiter=100000, callback=callback)
    return sol, count[0]


def scipy_direct(matrix, rhs):
    from scipy.sparse.linalg import factorized

    return factorized(matrix.tocsc())(rhs)


class TaichiMatrixFreeCG:
    """Eq. 15 solved with ``ti.linalg.MatrixFreeCG`` (no preconditioner: it has none).

    The matvec is a Taichi kernel gathering A p over each particle's springs from
    per-spring blocks (a, b, n) held in fields; fixed rows are zeroed.
    """

    def __init__(self, model, real=None):
        import taichi as ti

        self.ti = ti
        real = real or ti.f64
        self.model = model
        nparticles, m = model.n_particles, model.n_springs
        offsets, other, entry = adjacency(model)
        spring = np.where(entry >= 0, entry, -1 - entry)
        self.offsets = ti.field(ti.i32, shape=nparticles + 1)
        self.other = ti.field(ti.i32, shape=max(2 * m, 1))
        self.spring = ti.field(ti.i32, shape=max(2 * m, 1))
        self.mass = ti.field(real, shape=nparticles)
        self.free = ti.field(ti.i32, shape=nparticles)
        self.coef = ti.Vector.field(5, real, shape=max(m, 1))
        self.b = ti.field(real, shape=(nparticles, 3))
        self.x = ti.field(real, shape=(nparticles, 3))
        self.ax = ti.field(real, shape=(nparticles, 3))
        self.offsets.from_numpy(offsets.astype(np.int32))
        if m:
            self.other.from_numpy(other.astype(np.int32))
            self.spring.from_numpy(spring.astype(np.int32))
        self.mass.from_numpy(model.masses)
        self.free.from_numpy(model.free_mask().astype(np.int32))

        offsets_f, other_f, spring_f, mass_f, free_f, coef_f = (self.offsets, self.other, self.spring,
                                                                self.mass, self.free, self.coef)

        @ti.kernel
        def matvec(p: ti.template(), out: ti.template()):
            for i in range(nparticles):
                acc = ti.Vector.zero(real, 3)
                if free_f[i] != 0:
                    pi = ti.Vector([p[i, 0], p[i, 1], p[i, 2]])
                    acc = mass_f[i] * pi
                    for e in range(offsets_f[i], offsets_f[i + 1]):
                        c = coef_f[spring_f[e]]
                        j = other_f[e]
                        nn = ti.Vector([c[0], c[1], c[2]])
                        pj = ti.Vector([p[j, 0], p[j, 1], p[j, 2]]) * free_f[j]
                        dp = pi - pj
                        acc += c[3] * dp + c[4] * nn.dot(dp) * nn
                for k in ti.static(range(3)):
                    out[i, k] = acc[k]

        self.operator = ti.linalg.LinearOperator(matvec)
        self.matvecs = 0

        def counted(p, out):
            self.matvecs += 1
            matvec(p, out)

        self.operator._matvec = counted  # to count iterations: MatrixFreeCG does not report them

    def solve(self, x, v, dt, tol, definiteness_fix=True):
        """One Eq. 15 solve at state (x, v) from v, to ``tol`` times the first residual;
        returns ((n, 3) velocity v_{n+1}, iterations)."""
        model = self.model
        n, length, safe = spring_geometry(x, model.springs)
        c = np.where(safe, model.rest_lengths / np.where(safe, length, 1.0) - 1.0, 0.0)
        if definiteness_fix:
            c = np.minimum(c, 0.0)
        a = -dt * dt * model.stiffness * c
        b = dt * dt * model.stiffness * (1.0 + c) + dt * model.damping
        if model.n_springs:
            self.coef.from_numpy(np.concatenate([n, a[:, None], b[:, None]], axis=1))
        free = model.free_mask()
        rhs = model.masses[:, None] * v + dt * spring_forces(model, x, v, damping=False)
        rhs[~free] = 0.0
        guess = v.copy()
        guess[~free] = 0.0
        self.b.from_numpy(rhs)
        self.x.from_numpy(guess)
        self.operator._matvec(self.x, self.ax)
        first = np.linalg.norm(rhs - self.ax.to_numpy())
        self.matvecs = 0
        self.ti.linalg.MatrixFreeCG(self.operator, self.b, self.x, tol=tol * first, maxiter=100000)
        return self.x.to_numpy(), self.matvecs - 1  # one matvec is the initial residual


def pyamg_pcg(matrix, rhs, x0, tol):
    """SciPy CG preconditioned by pyamg's smoothed aggregation on ``matrix`` (3x3 blocks,
    the three translations as near-nullspace, pyamg's defaults otherwise, coarsest level
    at most 300 unknowns), to ``tol`` times the first residual, built here: the caller times assembly + setup + solve, as a
    sparse-matrix code pays them every step. Returns (solution, iterations)."""
    import pyamg
    from scipy.sparse.linalg import cg

    bsr = matrix.tobsr(blocksize=(3, 3))
    nodes = bsr.shape[0] // 3
    translations = np.kron(np.ones((nodes, 1)), np.eye(3))
    hierarchy = pyamg.smoothed_aggregation_solver(bsr, B=translations, max_coarse=300)
    count = [0]

    def callback(_):
        count[0] += 1

    sol, info = cg(bsr, rhs, x0=x0, rtol=0.0, atol=tol * first_residual(matrix, rhs, x0),
                   M=hierarchy.aspreconditioner(cycle="V"), maxiter=20000, callback=callback)
    return sol, count[0]


def disc_model(count, stiffness=1e4, seed=0):
    """An irregular mesh: ``count`` uniform random points in the unit disc (z = 0),
    Delaunay triangulated, its edges as springs (ks = ``stiffness`` N/m each, kd = 2),
    total mass 1 kg, gravity -z, the 4 rim points nearest 0, 90, 180 and 270 degrees
    pinned; the triangles are its surface."""
    import scipy.spatial

    import massspring as ms

    rng = np.random.default_rng(seed)
    radius, angle = np.sqrt(rng.random(count)), 2 * np.pi * rng.random(count)
    xy = np.stack([radius * np.cos(angle), radius * np.sin(angle)], axis=1)
    triangles = scipy.spatial.Delaunay(xy).simplices.astype(np.int64)
    edges = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    edges = np.unique(np.sort(edges, axis=1), axis=0)
    rim = [int(np.argmin(np.linalg.norm(xy - [np.cos(a), np.sin(a)], axis=1))) for a in np.arange(4) * np.pi / 2]
    positions = np.concatenate([xy, np.zeros((count, 1))], axis=1)
    return ms.Model(positions, edges, masses=1.0 / count, stiffness=stiffness, damping=2.0,
                    gravity=(0.0, 0.0, -9.81), fixed=rim, triangles=triangles)
