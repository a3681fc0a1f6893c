"""The matrix-free operator of Eq. 15 and the CG solver around it.

The operator A (``massspring.engine.operators.SystemOperator``: the implicit step's own
kernels) is reconstructed column by column (A e_k) and compared with the
independent numpy assembly of conftest.py.
"""

import numpy as np
import pytest

import massspring as ms
from conftest import FULL, PATHS, dense_system, free_dofs, random_system, simulation
from massspring.engine.operators import SystemOperator

EPS = np.finfo(np.float64).eps


class Operator:
    """A v -> A v for one model, state and dt, on the package's kernels (f64)."""

    def __init__(self, model, dt, definiteness_fix):
        self.model, self.dt, self.fix = model, dt, definiteness_fix
        self.system = SystemOperator(model, dt, definiteness_fix)
        self.n = model.n_particles
        self.keep = free_dofs(model)

    def apply(self, p):
        """(A p, p.Ap as returned by the kernel) for p (3n,), zero on fixed particles."""
        q, pq = self.system.apply(p.reshape(self.n, 3))
        return q.reshape(-1), pq

    def dense(self):
        """The free-DOF block of A, reconstructed from A e_k; also checks that A e_k
        vanishes on the fixed particles (their rows are dropped)."""
        cols = []
        for k in np.flatnonzero(self.keep):
            e = np.zeros(3 * self.n)
            e[k] = 1.0
            q, pq = self.apply(e)
            assert np.all(q[~self.keep] == 0)
            assert pq == pytest.approx(q[k], rel=1e-15, abs=0)
            cols.append(q[self.keep])
        return np.array(cols).T

    def random_vector(self, rng):
        p = rng.normal(size=3 * self.n)
        p[~self.keep] = 0.0
        return p


DT = 2e-2


@pytest.mark.fast_sample(seed=[0])
@pytest.mark.parametrize("fix", [True, False])
@pytest.mark.parametrize("seed", range(3))
def test_operator_symmetric(seed, fix):
    """p.Aq == q.Ap to round-off, on systems with compressed and stretched springs,
    with and without the definiteness fix (A is symmetric either way). Each dot
    product sums O(n) terms of size up to |p| |A| |q|, so the gap is bounded by a
    small multiple of n eps |p| ||A|| |q|."""
    model = random_system(seed, rest=(0.5, 2.0))
    op = Operator(model, DT, fix)
    rng = np.random.default_rng(seed)
    normA = np.linalg.norm(op.dense(), 2)
    for _ in range(3):
        p, q = op.random_vector(rng), op.random_vector(rng)
        Ap, pAp = op.apply(p)
        Aq, _ = op.apply(q)
        bound = 8 * p.size * EPS * np.linalg.norm(p) * normA * np.linalg.norm(q)
        assert abs(p @ Aq - q @ Ap) <= bound
        assert pAp == pytest.approx(p @ Ap, rel=1e-12)


@pytest.mark.fast_sample(seed=[0])
@pytest.mark.parametrize("fix", [True, False])
@pytest.mark.parametrize("seed", range(3))
def test_operator_equals_independent_dense_matrix(seed, fix):
    """Column by column, the kernels' A is the numpy assembly of Eq. 15 (relative to
    ||A||, up to the few roundings of each entry)."""
    model = random_system(10 + seed, rest=(0.5, 2.0))
    op = Operator(model, DT, fix)
    A_kernel = op.dense()
    A_numpy, _ = dense_system(model, DT, fix)
    np.testing.assert_allclose(A_kernel, A_numpy, rtol=0, atol=64 * EPS * np.abs(A_numpy).max())


def strongly_compressed(seed):
    """Every spring compressed to 1/2.5..1/3.5 of its rest length, stiff and with a
    large dt, so that the transverse term -dt^2 ks (l0/l - 1) of Eq. 13 dwarfs the
    masses: without the fix the matrix must be indefinite."""
    return random_system(seed, rest=(2.5, 3.5))


BIG_DT = 0.1


@pytest.mark.fast_sample(seed=[0])
@pytest.mark.parametrize("seed", range(3))
def test_definiteness_fix_gives_positive_definite_operator(seed):
    model = strongly_compressed(seed)
    op = Operator(model, BIG_DT, True)
    A = op.dense()
    np.testing.assert_allclose(A, dense_system(model, BIG_DT, True)[0], rtol=0, atol=64 * EPS * np.abs(A).max())
    # Each spring adds a PSD block (a I + b n n^T with a, b >= 0), so the smallest
    # eigenvalue is at least the smallest free mass.
    lam = np.linalg.eigvalsh(0.5 * (A + A.T)).min()
    min_mass = model.masses[model.free_mask()].min()
    assert lam >= min_mass * (1 - 1e-10), (lam, min_mass)
    # CG can solve it: one implicit step converges
    for path in PATHS:
        sim = simulation(model, path, dt=BIG_DT, cg_tol=1e-10, definiteness_fix=True)
        sim.step()
        assert sim.solver_stats.converged, (path, sim.solver_stats)


@FULL
@pytest.mark.fast_sample(seed=[0])
@pytest.mark.parametrize("seed", range(3))
def test_without_fix_strongly_compressed_operator_is_indefinite(seed):
    """The counterpart: the same systems without the fix have a negative eigenvalue,
    so the positive-definiteness test above is meaningful."""
    model = strongly_compressed(seed)
    op = Operator(model, BIG_DT, False)
    A = op.dense()
    np.testing.assert_allclose(A, dense_system(model, BIG_DT, False)[0], rtol=0, atol=64 * EPS * np.abs(A).max())
    lam = np.linalg.eigvalsh(0.5 * (A + A.T))
    assert lam.min() < -1.0 and lam.max() > 0, (lam.min(), lam.max())
    # and CG notices: the step reports the indefinite system instead of a solution
    for path in PATHS:
        sim = simulation(model, path, dt=BIG_DT, cg_tol=1e-10, definiteness_fix=False)
        sim.step()
        stats = sim.solver_stats
        assert not stats.converged and stats.reason == "indefinite", (path, stats)
        assert sim.cg_failures == 1


def test_zero_length_springs_in_the_operator():
    """Springs of length 0 and 1e-13 (<= 1e-12) have no direction. The one of rest
    length 0.5 adds nothing to A; the one of rest length 0 (f = ks d, linear) adds its
    dt^2 ks [[I, -I], [-I, I]] blocks all the same. A is that of the model without the
    two plus those blocks, assembled here by hand."""
    x = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 0.0, 1e-13], [0.5, 0.7, 0.2]])
    springs = [[0, 1], [2, 3], [0, 4], [4, 2], [1, 4]]
    kw = dict(masses=[1.0, 2.0, 1.5, 0.7, 1.2], damping=0.5, gravity=(0.0, 0.0, -9.81), fixed=[4])
    model = ms.Model(x, springs, stiffness=[300.0, 200.0, 100.0, 150.0, 120.0],
                     rest_lengths=[0.5, 0.0, 0.6, 0.9, 1.0], **kw)
    without = ms.Model(x, [[0, 4], [4, 2], [1, 4]], stiffness=[100.0, 150.0, 120.0],
                       rest_lengths=[0.6, 0.9, 1.0], **kw)
    linear = DT * DT * 200.0 * np.kron([[1.0, -1.0], [-1.0, 1.0]], np.eye(3))  # particles 2, 3 (free dofs 6-11)
    for fix in (True, False):
        A = Operator(model, DT, fix).dense()
        A_without = dense_system(without, DT, fix)[0]
        A_without[6:12, 6:12] += linear
        np.testing.assert_allclose(A, A_without, rtol=0, atol=64 * EPS * np.abs(A).max())
        np.testing.assert_allclose(A, dense_system(model, DT, fix)[0], rtol=0, atol=64 * EPS * np.abs(A).max())


def test_block_jacobi_blocks_and_right_hand_side():
    """The refresh's block-Jacobi inverse is the inverse of A's 3x3 diagonal blocks and
    its right-hand side is Eq. 15's M v + dt f - dt D v (zero on fixed particles)."""
    model = random_system(21, rest=(0.5, 2.0))
    op = Operator(model, DT, True)
    A, b = dense_system(model, DT, True)
    free = model.free_mask()
    minv = op.system.inverse_diagonal_blocks()
    A_full = np.zeros((3 * op.n, 3 * op.n))
    A_full[np.ix_(op.keep, op.keep)] = A
    for i in np.flatnonzero(free):
        block = A_full[3 * i:3 * i + 3, 3 * i:3 * i + 3]
        np.testing.assert_allclose(minv[i] @ block, np.eye(3), rtol=0, atol=1e-13)
    b_kernel = op.system.rhs().reshape(-1)
    np.testing.assert_allclose(b_kernel[op.keep], b, rtol=0, atol=64 * EPS * np.abs(b).max())
    assert np.all(b_kernel[~op.keep] == 0)


# ----------------------------------------------------------------------------- CG behaviour


def cloth(n_side=12, seed=0):
    """An n x n grid in the xy plane with structural and shear springs, two corners
    pinned, masses over three orders of magnitude and stiffness over two (smoothly
    varying across the cloth plus noise), under gravity and slightly damped, with
    small random initial velocities (from rest a flat cloth at rest length has no
    transverse stiffness and the first solve would be trivial)."""
    rng = np.random.default_rng(seed)
    idx = np.arange(n_side * n_side).reshape(n_side, n_side)
    gx, gy = np.meshgrid(np.arange(n_side), np.arange(n_side), indexing="ij")
    h = 0.1
    x = np.stack([gx * h, gy * h, np.zeros_like(gx, dtype=float)], axis=-1).reshape(-1, 3)
    springs = np.concatenate([
        np.stack([idx[:-1, :].ravel(), idx[1:, :].ravel()], 1),
        np.stack([idx[:, :-1].ravel(), idx[:, 1:].ravel()], 1),
        np.stack([idx[:-1, :-1].ravel(), idx[1:, 1:].ravel()], 1),
        np.stack([idx[1:, :-1].ravel(), idx[:-1, 1:].ravel()], 1),
    ])
    masses = 10.0 ** (3.0 * gx.ravel() / (n_side - 1) - 2.0 + 0.3 * rng.normal(size=n_side * n_side))
    mid = 0.5 * (gy.ravel()[springs[:, 0]] + gy.ravel()[springs[:, 1]]) / (n_side - 1)
    ks = 10.0 ** (2.0 + 2.0 * mid + 0.2 * rng.normal(size=len(springs)))
    return ms.Model(x, springs, masses=masses, stiffness=ks, damping=0.1,
                    velocities=0.1 * rng.normal(size=x.shape),
                    gravity=(0.0, 0.0, -9.81), fixed=[idx[0, 0], idx[0, -1]])


@FULL
@pytest.mark.parametrize("path", PATHS)
def test_block_jacobi_reduces_cg_iterations(path):
    model = cloth()
    counts = {}
    for pre in ("block-jacobi", "none"):
        sim = simulation(model, path, dt=1e-2, cg_tol=1e-8, cg_max_iter=2000, preconditioner=pre)
        sim.step(3)
        assert sim.cg_failures == 0, (pre, sim.solver_stats)
        counts[pre] = sum(sim.cg_iterations)
    assert counts["block-jacobi"] < 0.5 * counts["none"], counts


@pytest.mark.fast_sample(path=["serial"])
@pytest.mark.parametrize("path", PATHS)
def test_preconditioners_agree(path):
    """Both preconditioners solve the same system: after one step each velocity is
    within cond(A) * cg_tol (relative, 2-norm) of the exact solution, so they are
    within twice that of each other; cond(A) is computed (about 1e4 here)."""
    model = cloth()
    tol = 1e-8
    out = []
    for pre in ("block-jacobi", "none"):
        sim = simulation(model, path, dt=1e-2, cg_tol=tol, cg_max_iter=2000, preconditioner=pre)
        sim.step()
        assert sim.solver_stats.converged
        out.append(sim.velocities)
    A, _ = dense_system(model, 1e-2, True)
    bound = 2 * np.linalg.cond(A) * (tol + 1e-12) * np.linalg.norm(out[0])
    assert np.linalg.norm(out[0] - out[1]) <= bound


@pytest.mark.fast_sample(path=["serial"])
@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("preconditioner", ["block-jacobi", "none"])
def test_warm_start_at_solution_needs_no_iterations(preconditioner, path):
    """A free rigid pair at rest length, no gravity, both particles with the same
    velocity u: f = 0 and A u = M u (the springs see no relative velocity), so the
    warm start v_n = u already solves Eq. 15 (to round-off, which the tolerance relative
    to the first residual must not chase) and CG does no iteration."""
    u = np.array([0.3, -0.2, 0.1])
    # particle 2 is fixed and unconnected: it changes nothing but makes the run use
    # the kernel variant (damping, no gravity, fixed) test_exact.py already compiled
    model = ms.Model([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [5.0, 5.0, 5.0]], [[0, 1]], masses=[1.0, 2.0, 1.0],
                     stiffness=1e3, damping=1.0, velocities=[u, u, u], gravity=(0.0, 0.0, 0.0), fixed=[2])
    sim = simulation(model, path, dt=1e-2, preconditioner=preconditioner)
    sim.step(5)
    assert sim.cg_iterations == [0] * 5
    momentum = np.linalg.norm(model.masses[:2, None] * u)  # ||S b|| = ||M u||: the residual's round-off scale
    assert sim.solver_stats.converged and sim.solver_stats.first_residual <= 1e-14 * momentum
    np.testing.assert_allclose(sim.velocities, [u, u, 0 * u], rtol=0, atol=1e-14)
    expected = model.positions + 5 * 1e-2 * np.array([u, u, 0 * u])
    np.testing.assert_allclose(sim.positions, expected, rtol=0, atol=1e-14)

