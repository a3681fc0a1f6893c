"""The smoothed-aggregation multigrid preconditioner: its structure (numpy), its cycle
against an independent dense numpy cycle, symmetry and positive definiteness, and the
solves and iteration counts it gives."""

import numpy as np
import pytest

import massspring as ms
from conftest import FULL, free_dofs
from massspring.kernels import cg, operator
from massspring.engine.operators import SystemOperator
from massspring.solvers import aggregation, multigrid

DT = 1 / 60


def swinging_cloth(resolution, stiffness=1e4, steps=8, pin="corners"):
    """A cloth model at a swung, non-flat state (after a few implicit steps), so that
    springs are stretched and turned: the operator has its transverse terms."""
    scene = ms.load_scene("cloth").with_params(resolution=resolution, stiffness=stiffness, pin=pin)
    sim = scene.simulation(dt=DT)
    sim.step(steps)
    model = scene.model()
    state = ms.Model(sim.positions, model.springs, masses=model.masses, stiffness=model.stiffness,
                     damping=model.damping, rest_lengths=model.rest_lengths, velocities=sim.velocities,
                     gravity=model.gravity, fixed=model.fixed)
    sim.close()
    return state


def tentative_blocks(positions, transfer):
    """T's blocks (numpy reference) for level 0 at ``positions``."""
    modes, _ = aggregation.rigid_modes(positions, transfer.agg, transfer.nc)
    return aggregation.tentative(transfer.agg, transfer.nc, modes)[0]


# ----------------------------------------------------------------------------- structure


def test_aggregates_cover_the_free_particles_and_tentative_prolongation_is_orthonormal():
    model = swinging_cloth(12, steps=0)
    level = aggregation.build(model, DT, max_coarse=100).levels[0]
    t = level.transfer
    free = model.free_mask()
    assert np.all(t.agg[free] >= 0) and np.all(t.agg[~free] == -1)
    sizes = np.bincount(t.agg[free])
    assert sizes.min() >= 2 and sizes.max() <= 13  # 3x3 patches and a few extras
    # T^T T = I: per aggregate, the stacked blocks are orthonormal columns
    tent = tentative_blocks(model.positions, t)
    dense = np.zeros((3 * model.n_particles, 6 * t.nc))
    for i in np.flatnonzero(free):
        dense[3 * i:3 * i + 3, 6 * t.agg[i]:6 * t.agg[i] + 6] = tent[i]
    np.testing.assert_allclose(dense.T @ dense, np.eye(6 * t.nc), atol=1e-12)
    # and they span the rigid modes of each aggregate: T T^T B = B
    modes, _ = aggregation.rigid_modes(model.positions, t.agg, t.nc)
    for k in range(6):
        b = np.zeros(3 * model.n_particles)
        b.reshape(-1, 3)[free] = modes[free, :, k]
        np.testing.assert_allclose(dense @ (dense.T @ b), b, atol=1e-10)


def without_couplings(a, pairs):
    """The dense 3n x 3n ``a`` with the couplings (i, j) of ``pairs`` (each once) taken out,
    springs and all: the off-diagonal blocks zeroed and taken off the diagonal blocks
    (A_ii + A_ij)."""
    out = a.copy()
    for i, j in pairs:
        bi, bj = slice(3 * i, 3 * i + 3), slice(3 * j, 3 * j + 3)
        out[bi, bi] += a[bi, bj]
        out[bj, bj] += a[bj, bi]
        out[bi, bj] = out[bj, bi] = 0.0
    return out


def left_out(level, rows, cols, smoothing):
    """The couplings (i < j) of the adjacency ``rows``/``cols`` that level 0 leaves out of
    P's smoothing (``smoothing``) or of the Galerkin products."""
    kept = level.entry[level.smooth] if smoothing else level.entry
    out = np.ones(len(cols), dtype=bool)
    out[kept] = False
    owner = np.repeat(np.arange(len(rows) - 1), np.diff(rows))
    return {(min(i, j), max(i, j)) for i, j in zip(owner[out], cols[out])}


def block_pattern(m, size):
    """The (I, J) blocks of ``m`` (size x size blocks) that are not zero."""
    nb = m.shape[0] // size
    norms = np.abs(m.reshape(nb, size, nb, size)).sum(axis=(1, 3))
    return set(zip(*np.nonzero(norms > 1e-12 * norms.max())))


@pytest.mark.parametrize("filter_weak", [False, True])
def test_galerkin_pattern_and_numpy_product_match_dense_products(filter_weak):
    """aggregation.galerkin (the index lists of the kernels, evaluated in numpy) is the
    dense P^T A' P of the dense P = T - s D^-1 A_s T, for the rest operator A of a cloth:
    without the filter A_s = A' = A; with it, A_s is A without its weak couplings (the
    bending springs) and A' keeps those of them that add no block to P^T A_s P."""
    model = swinging_cloth(10, steps=0)
    hierarchy = aggregation.build(model, DT, max_coarse=100, filter_weak=filter_weak)
    level = hierarchy.levels[0]
    t = level.transfer
    diag, off, rows, cols = aggregation.rest_operator(model, DT, model.free_mask())
    n = model.n_particles
    a = np.zeros((3 * n, 3 * n))
    owner = np.repeat(np.arange(n), np.diff(rows))
    for e, (i, j) in enumerate(zip(owner, cols)):
        a[3 * i:3 * i + 3, 3 * j:3 * j + 3] += off[e]
    for i in range(n):
        a[3 * i:3 * i + 3, 3 * i:3 * i + 3] += diag[i]
    a_s = without_couplings(a, left_out(level, rows, cols, True))
    a_k = without_couplings(a, left_out(level, rows, cols, False))
    free = model.free_mask()
    bending = {tuple(sorted(p)) for p, length in zip(model.springs.tolist(), model.rest_lengths)
               if length > 1.5 / 9 and free[p].all()}  # the spacing is 1/9, bend springs span 2; pins hold theirs
    if filter_weak:
        assert left_out(level, rows, cols, True) == bending
        assert left_out(level, rows, cols, False) < bending  # some kept
    else:
        assert not left_out(level, rows, cols, True)
    dinv = np.linalg.inv(diag)
    scale = 0.5
    blocks = tentative_blocks(model.positions, t)
    diag_s, diag_k, off_k = aggregation.filtered_operator(level, diag, off, rows)
    p_blocks = aggregation.smooth_prolongation(level, diag_s, off_k, dinv, scale, blocks)
    c_diag, c_off = aggregation.galerkin(level, diag_k, off_k, p_blocks)
    tent = np.zeros((3 * n, 6 * t.nc))
    for i in np.flatnonzero(t.agg >= 0):
        tent[3 * i:3 * i + 3, 6 * t.agg[i]:6 * t.agg[i] + 6] = blocks[i]
    dinv_dense = np.zeros_like(a)
    for i in range(n):
        dinv_dense[3 * i:3 * i + 3, 3 * i:3 * i + 3] = dinv[i]
    p_dense = tent - scale * dinv_dense @ a_s @ tent
    p_from_blocks = np.zeros_like(p_dense)
    for i in range(n):
        for k in range(t.p_rows[i], t.p_rows[i + 1]):
            p_from_blocks[3 * i:3 * i + 3, 6 * t.p_cols[k]:6 * t.p_cols[k] + 6] = p_blocks[k]
    np.testing.assert_allclose(p_from_blocks, p_dense, atol=1e-12 * np.abs(p_dense).max())
    ac = p_dense.T @ a_k @ p_dense
    nxt = hierarchy.levels[1]
    ac_from_blocks = np.zeros_like(ac)
    c_owner = np.repeat(np.arange(nxt.n), np.diff(nxt.off_rows))
    for e, (i, j) in enumerate(zip(c_owner, nxt.off_cols)):
        ac_from_blocks[6 * i:6 * i + 6, 6 * j:6 * j + 6] = c_off[e]
    for i in range(nxt.n):
        ac_from_blocks[6 * i:6 * i + 6, 6 * i:6 * i + 6] = c_diag[i]
    np.testing.assert_allclose(ac_from_blocks, ac, atol=1e-11 * np.abs(ac).max())
    # the weak couplings kept add no coarse block: the pattern is that of P^T A_s P
    assert block_pattern(ac, 6) == block_pattern(p_dense.T @ a_s @ p_dense, 6)
    if filter_weak:  # and the filter leaves the coarse level sparser than the full A's
        assert len(block_pattern(ac, 6)) < len(block_pattern(p_dense.T @ a @ p_dense, 6))


@FULL
def test_tentative_kernels_match_the_numpy_reference():
    """T, the coarse candidates R and the aggregates' centres that the kernels build at
    the current positions equal the numpy reference (rigid modes about each aggregate's
    centre, modified Gram-Schmidt per aggregate), on both transfers of a three-level
    hierarchy."""
    model = swinging_cloth(40)
    system = SystemOperator(model, DT, preconditioner="multigrid")
    pre = system._preconditioner
    levels, g = pre.hierarchy.levels, pre.g
    assert len(levels) == 3
    t0, t1 = levels[0].transfer, levels[1].transfer
    modes0, centres1 = aggregation.rigid_modes(model.positions, t0.agg, t0.nc)
    blocks0, cand1 = aggregation.tentative(t0.agg, t0.nc, modes0)
    modes1, centres2 = aggregation.coarse_modes(cand1, centres1, t1.agg, t1.nc)
    blocks1, cand2 = aggregation.tentative(t1.agg, t1.nc, modes1)
    (b1, e1), (b2, e2) = pre.plan.node_range[1], pre.plan.node_range[2]
    has0, has1 = t0.agg >= 0, t1.agg >= 0
    cand = g.c_cand.to_numpy()
    np.testing.assert_allclose(g.t0.to_numpy()[:model.n_particles][has0], blocks0[has0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(cand[b1:e1], cand1, rtol=0, atol=1e-12 * np.abs(cand1).max())
    np.testing.assert_allclose(g.tc.to_numpy()[b1:e1][has1], blocks1[has1], rtol=0, atol=1e-10)
    np.testing.assert_allclose(cand[b2:e2], cand2, rtol=0, atol=1e-10 * np.abs(cand2).max())
    centre = g.c_centre.to_numpy()
    np.testing.assert_allclose(centre[b1:e1], centres1, rtol=0, atol=1e-14)
    np.testing.assert_allclose(centre[b2:e2], centres2, rtol=0, atol=1e-14)
    system.close()


@FULL
def test_composite_tentative_prolongation_spans_rigid_motions_of_coarse_aggregates():
    """Independent of how the kernels shift centres: T0 T1 (level 2 -> particles) has
    orthonormal columns and its range holds every rigid motion (3 translations, 3
    rotations about the origin) of each level-2 aggregate's particles. Candidates that
    disagree between members (rotations about each member's own centre) fail this."""
    model = swinging_cloth(40)
    system = SystemOperator(model, DT, preconditioner="multigrid")
    pre = system._preconditioner
    levels, g = pre.hierarchy.levels, pre.g
    t0, t1 = levels[0].transfer, levels[1].transfer
    b1, e1 = pre.plan.node_range[1]
    n = model.n_particles
    tent0 = np.zeros((3 * n, 6 * t0.nc))
    blocks0 = g.t0.to_numpy()
    for i in np.flatnonzero(t0.agg >= 0):
        tent0[3 * i:3 * i + 3, 6 * t0.agg[i]:6 * t0.agg[i] + 6] = blocks0[i]
    tent1 = np.zeros((6 * t0.nc, 6 * t1.nc))
    blocks1 = g.tc.to_numpy()[b1:e1]
    for i in np.flatnonzero(t1.agg >= 0):
        tent1[6 * i:6 * i + 6, 6 * t1.agg[i]:6 * t1.agg[i] + 6] = blocks1[i]
    composite = tent0 @ tent1
    np.testing.assert_allclose(composite.T @ composite, np.eye(6 * t1.nc), rtol=0, atol=1e-12)
    owner = np.where(t0.agg >= 0, t1.agg[np.maximum(t0.agg, 0)], -1)  # level-2 aggregate of each particle
    x = model.positions
    for a in range(t1.nc):
        inside = owner == a
        for k in range(6):
            b = np.zeros((n, 3))
            if k < 3:
                b[inside, k] = 1.0
            else:
                b[inside] = np.cross(np.eye(3)[k - 3], x[inside])
            b = b.reshape(-1)
            np.testing.assert_allclose(composite @ (composite.T @ b), b, rtol=0, atol=1e-9 * np.abs(b).max())
    system.close()


@pytest.mark.full
def test_collinear_aggregates_leave_idle_unknowns_and_a_positive_cycle():
    """A straight chain: every aggregate is collinear, so the rotation about the chain
    is no candidate (a zero column of T, a zero row of R) on every level; those coarse
    unknowns are idle (unit pivots, not failures) and the cycle stays symmetric
    positive definite."""
    model = ms.load_scene("chain").with_params(count=600).model()
    system = SystemOperator(model, 0.01, preconditioner="multigrid")
    pre = system._preconditioner
    assert pre.plan.levels >= 3 and pre.factor_failed == 0
    cand, tc = pre.g.c_cand.to_numpy(), pre.g.tc.to_numpy()
    b1, e1 = pre.plan.node_range[1]
    assert np.all(cand[b1:e1, 3, :] == 0) and np.all(tc[b1:e1, :, 3] == 0)
    assert np.all(np.abs(np.diagonal(cand[b1:e1], axis1=1, axis2=2)[:, [0, 1, 2, 4, 5]]) > 0)
    rng = np.random.default_rng(3)
    keep = free_dofs(model).reshape(-1, 3)
    for _ in range(3):
        x, y = rng.normal(size=keep.shape) * keep, rng.normal(size=keep.shape) * keep
        bx, by = system.precondition(x), system.precondition(y)
        assert abs(np.sum(x * by) - np.sum(y * bx)) <= 1e-12 * np.linalg.norm(x) * np.linalg.norm(by)
        assert np.sum(x * bx) > 0
    system.close()


# -------------------------------------------------------------------------------- cycle


def dense_operator(system, model):
    """The dense 3n x 3n A (zero rows and columns at pinned particles), from A e_k."""
    n = model.n_particles
    a = np.zeros((3 * n, 3 * n))
    for k in np.flatnonzero(free_dofs(model)):
        e = np.zeros(3 * n)
        e[k] = 1.0
        a[:, k] = system.apply(e.reshape(n, 3))[0].reshape(-1)
    return a


def chebyshev_smooth(a, dinv, b, x, rho, ratio=multigrid.CHEB_RATIO, degree=multigrid.NU):
    """Chebyshev smoothing for A x = b in D^-1 A on [rho/ratio, rho] (Saad Alg. 12.1), dense."""
    low = rho / ratio
    theta, delta = (rho + low) / 2, (rho - low) / 2
    sigma = theta / delta
    rh = 1 / sigma
    r = b - a @ x
    d = dinv @ r / theta
    for k in range(degree):
        x = x + d
        r = r - a @ d
        if k == degree - 1:
            break
        rh_new = 1 / (2 * sigma - rh)
        d = rh_new * rh * d + 2 * rh_new / delta * (dinv @ r)
        rh = rh_new
    return x


@FULL
def test_two_level_cycle_matches_a_dense_numpy_cycle():
    """On a cloth whose hierarchy has two levels (the coarse one solved exactly), the
    kernels' z = B r equals the same cycle written densely: P = T - (4/3)/rho D^-1 A_s T,
    A_c = P^T A' P (A_s, A': A without the couplings the hierarchy leaves out of P's
    smoothing and of the Galerkin product), Chebyshev(3) before and after x += P A_c^-1 P^T (b - A x), rho from
    the same row-sum bound (at most 2, the bound the definiteness fix proves)."""
    model = swinging_cloth(20)
    hierarchy = aggregation.build(model, DT)
    assert len(hierarchy.levels) == 2
    system = SystemOperator(model, DT, preconditioner="multigrid")
    a = dense_operator(system, model)
    n = model.n_particles
    keep = free_dofs(model)
    dinv = np.zeros_like(a)
    bound = 0.0
    for i in np.flatnonzero(model.free_mask()):
        block = a[3 * i:3 * i + 3, 3 * i:3 * i + 3]
        inv = np.linalg.inv(block)
        dinv[3 * i:3 * i + 3, 3 * i:3 * i + 3] = inv
        row = sum(np.abs(inv @ a[3 * i:3 * i + 3, 3 * j:3 * j + 3]).sum(axis=1).max()
                  for j in range(n) if np.any(a[3 * i:3 * i + 3, 3 * j:3 * j + 3]))
        bound = max(bound, row)
    rho = min(2.0, bound)
    t = hierarchy.levels[0].transfer
    blocks = tentative_blocks(model.positions, t)
    tent = np.zeros((3 * n, 6 * t.nc))
    for i in np.flatnonzero(t.agg >= 0):
        tent[3 * i:3 * i + 3, 6 * t.agg[i]:6 * t.agg[i] + 6] = blocks[i]
    diag, off, rows, cols = aggregation.rest_operator(model, DT, model.free_mask())
    a_s = without_couplings(a, left_out(hierarchy.levels[0], rows, cols, True))
    a_k = without_couplings(a, left_out(hierarchy.levels[0], rows, cols, False))
    p = tent - (multigrid.OMEGA / rho) * dinv @ a_s @ tent
    ac = p.T @ a_k @ p
    rng = np.random.default_rng(5)
    for _ in range(3):
        r = rng.normal(size=3 * n) * keep
        x = chebyshev_smooth(a, dinv, r, np.zeros(3 * n), rho)
        x = x + p @ np.linalg.solve(ac, p.T @ (r - a @ x))
        x = chebyshev_smooth(a, dinv, r, x, rho) * keep
        z = system.precondition(r.reshape(n, 3)).reshape(-1)
        np.testing.assert_allclose(z, x, rtol=0, atol=1e-9 * np.abs(x).max())
    system.close()


@pytest.mark.fast_sample(resolution=[12])
@pytest.mark.parametrize("resolution, w_cycle", [(12, False), (40, False), (40, True)])
def test_cycle_is_symmetric_and_positive_definite(resolution, w_cycle, monkeypatch):
    """x . B y = y . B x to round-off and x . B x > 0, on random vectors of the free
    directions; at 12^2 the cycle is the smoother alone, at 40^2 it has three levels
    (Lanczos bounds on level 1), as the default V-cycle and as a W-cycle."""
    monkeypatch.setattr(multigrid, "W_CYCLE", w_cycle)
    model = swinging_cloth(resolution)
    levels = len(aggregation.build(model, DT).levels)
    assert levels == (1 if resolution == 12 else 3)  # 12^2: smoothing alone, no coarse level
    system = SystemOperator(model, DT, preconditioner="multigrid")
    keep = free_dofs(model).reshape(-1, 3)
    for _, bx in symmetric_positive_definite(system, keep, np.random.default_rng(resolution)):
        assert np.all(bx[~keep] == 0)
    system.close()


def symmetric_positive_definite(system, keep, rng, count=4):
    """Yields (x, B x) for ``count`` random x on the free directions ``keep`` ((n, 3)
    bool), B = ``system.precondition``, after checking x . B y = y . B x to round-off and
    x . B x > 0 against another random y."""
    for _ in range(count):
        x, y = rng.normal(size=keep.shape) * keep, rng.normal(size=keep.shape) * keep
        bx, by = system.precondition(x), system.precondition(y)
        scale = np.linalg.norm(x) * np.linalg.norm(by)
        assert abs(np.sum(x * by) - np.sum(y * bx)) <= 1e-12 * scale
        assert np.sum(x * bx) > 0
        yield x, bx


@pytest.mark.full
def test_stale_coarse_levels_keep_the_cycle_symmetric_positive_definite():
    """The module docstring's claim for a hierarchy kept across steps: set up at one state
    of a swinging 40^2 cloth, then the operator refreshed at a state four steps later with
    only level 0's D^-1 and rho (``fine_level``), the cycle is still symmetric and
    positive definite on the free directions (and not the fresh one's)."""
    early, late = swinging_cloth(40, steps=4), swinging_cloth(40, steps=8)
    system = SystemOperator(early, DT, preconditioner="multigrid")
    fresh = SystemOperator(late, DT, preconditioner="multigrid")
    dev, mg = system._dev, system._preconditioner
    for field, values in ((dev.x, late.positions), (dev.v, late.velocities)):
        field.from_numpy(np.pad(values, ((0, field.shape[0] - len(values)), (0, 0))))
    cg.cg_refresh(dev, system._cfg, dev.x, DT, 0.0, operator.LINEARISED)
    mg.fine_level()
    keep = free_dofs(late).reshape(-1, 3)
    for x, bx in symmetric_positive_definite(system, keep, np.random.default_rng(3)):
        assert np.abs(bx - fresh.precondition(x)).max() > 1e-3 * np.abs(bx).max()
    system.close()
    fresh.close()


# -------------------------------------------------------------------------------- solves


@pytest.mark.fast_sample(scene_name=["cloth", "stiffcloth"])
@pytest.mark.parametrize("scene_name, params", [
    ("cloth", {"resolution": 20}), ("stiffcloth", {"resolution": 20}), ("compressed", {"resolution": 20}),
    ("crumpled", {"resolution": 20}), ("cube", {"resolution": 5}), ("chain", {"count": 80}),
    ("chain", {"count": 600}), ("drape", {"resolution": 24}), ("flag", {"resolution": 24}),
])
def test_multigrid_solves_eq15_as_block_jacobi_does(scene_name, params):
    """Same steps, tolerance 1e-12: the two preconditioners give the same velocities to
    what the tolerance allows (cond(A) x 1e-12 relative to the first residual, which the
    stiff compressed cloth's h^2 K v_n makes up to 11 ||b|| in these steps; cond < 1e6 here)."""
    scene = ms.load_scene(scene_name).with_params(**params)
    out = []
    for preconditioner in ("multigrid", "block-jacobi"):
        sim = scene.simulation(integrator="implicit", preconditioner=preconditioner, cg_tol=1e-12)
        sim.step(5)
        assert sim.cg_failures == 0, (preconditioner, sim.solver_stats)
        out.append((sim.positions, sim.velocities, sim.cg_iterations))
        sim.close()
    (x_mg, v_mg, its_mg), (x_bj, v_bj, its_bj) = out
    assert np.abs(v_mg - v_bj).max() <= 1e-4 * np.abs(v_bj).max()
    assert np.abs(x_mg - x_bj).max() <= 1e-4 * np.abs(x_bj - scene.model().positions).max()
    if scene_name not in ("chain", "drape"):  # a chain's hierarchy is too shallow to help much
        assert sum(its_mg) < sum(its_bj)


@pytest.mark.full
@pytest.mark.parametrize("friction", [0.0, 0.5])
def test_multigrid_with_every_particle_in_contact(friction):
    """A 32 x 32 cloth (three levels) lying on a plane and, in the middle, on the cap of a
    sphere poking through it, sliding: every particle's normal is filtered. The coarse
    levels must be built from the filtered operator and drop the rigid modes the filter
    removes (before the fix: 400 iterations without converging, then "indefinite" at
    once), and the solve must match block-Jacobi's."""
    flat = ms.load_scene("cloth").with_params(resolution=32, pin="none").model()
    slide = np.random.default_rng(0).normal(scale=0.1, size=flat.positions.shape) * [1.0, 1.0, 0.0]
    x = flat.positions.copy()
    cap = 0.25 ** 2 - (x[:, 0] - 0.5) ** 2 - (x[:, 1] - 0.5) ** 2
    x[:, 2] = np.maximum(x[:, 2], -0.2 + np.sqrt(np.maximum(cap, 0.0)))  # on the sphere where it pokes through
    model = ms.Model(x, flat.springs, masses=flat.masses, stiffness=flat.stiffness,
                     damping=flat.damping, rest_lengths=flat.rest_lengths, velocities=slide, gravity=flat.gravity,
                     colliders=[ms.Plane((0, 0, 0), (0, 0, 1), friction=friction),
                                ms.Sphere((0.5, 0.5, -0.2), 0.25, friction=friction)])
    assert len(aggregation.build(model, DT).levels) == 3
    out = []
    for preconditioner in ("multigrid", "block-jacobi"):
        sim = ms.Simulation(model, integrator="implicit", dt=DT, preconditioner=preconditioner, cg_tol=1e-10,
                            cg_max_iter=1000)
        sim.step(5)
        assert sim.cg_failures == 0, (preconditioner, sim.solver_stats)
        out.append((sim.velocities, sim.cg_iterations))
        sim.close()
    (v_mg, its_mg), (v_bj, _) = out
    assert max(its_mg) <= 20, its_mg
    assert np.abs(v_mg - v_bj).max() <= 1e-4 * np.abs(v_bj).max()


@FULL
@pytest.mark.parametrize("stiffness", [1e4, 1e6])
@pytest.mark.parametrize("resolution", [16, 32])
def test_iteration_counts_stay_low(resolution, stiffness):
    """A regression bound, far below block-Jacobi's 150-350 iterations at 32^2: the cycle
    keeps the count flat (measured 8-12 here, 10-16 up to 128^2 in benchmarks)."""
    scene = ms.load_scene("cloth").with_params(resolution=resolution, stiffness=stiffness)
    sim = scene.simulation(integrator="implicit", preconditioner="multigrid")
    sim.step(20)
    assert sim.cg_failures == 0
    assert max(sim.cg_iterations) <= 20, sim.cg_iterations
    sim.close()


@FULL
def test_lanczos_goes_on_while_its_estimate_grows(monkeypatch):
    """With too few Lanczos steps the coarse levels' rho is low, and the Chebyshev
    smoother then amplifies their top modes: with 3 steps and no more, one step of a
    swinging 64^2 cloth at ks 1e6 took 46 CG iterations (the default: 7-8). Going on
    while the largest Ritz value still grows keeps the counts of many more steps, from
    the same 3-step start, and stops there once it has settled."""
    scene = ms.load_scene("cloth").with_params(resolution=64, stiffness=1e6)

    def run():
        sim = scene.simulation(integrator="implicit", dt=DT, preconditioner="multigrid")
        steps = []
        for _ in range(4):
            sim.step(1)
            steps.append(list(sim.stepper.preconditioner.lanczos_steps))
        counts = sim.cg_iterations
        sim.close()
        return counts, steps

    reference, _ = run()
    monkeypatch.setattr(multigrid, "LANCZOS_MAX", 60)
    monkeypatch.setattr(multigrid, "LANCZOS_STEPS", 3)
    monkeypatch.setattr(multigrid, "LANCZOS_RTOL", np.inf)  # stop at 3: the estimate is not checked
    fixed, steps = run()
    assert all(n == 3 for level in steps for n in level), steps
    assert max(fixed) > 4 * max(reference), (fixed, reference)
    monkeypatch.setattr(multigrid, "LANCZOS_RTOL", 0.01)
    adaptive, steps = run()
    assert max(adaptive) <= max(reference) + 1, (adaptive, reference)
    assert all(3 <= n < 60 for level in steps for n in level) and max(max(level) for level in steps) > 3, steps


@FULL
@pytest.mark.parametrize("loops", ["serial", "parallel"])
def test_one_cycle_per_iteration_and_per_cg_start_that_goes_on(loops, monkeypatch):
    """CG applies the cycle once per iteration and once after each true-residual
    restart (``cg_begin``) that it goes on from: the restart that ends a solve, the
    convergence check, runs no cycle (it ran one, which nothing used, before)."""
    from massspring.solvers import cg as driver

    counts = {"apply": 0, "begin": 0}
    apply, begin = multigrid.Multigrid.apply, driver.cg.cg_begin

    def counting_apply(self):
        counts["apply"] += 1
        return apply(self)

    def counting_begin(*args):
        counts["begin"] += 1
        return begin(*args)

    monkeypatch.setattr(multigrid.Multigrid, "apply", counting_apply)
    monkeypatch.setattr(driver.cg, "cg_begin", counting_begin)
    sim = ms.load_scene("cloth").with_params(resolution=16).simulation(integrator="implicit", dt=DT, loops=loops,
                                                                      preconditioner="multigrid")
    for _ in range(5):
        counts.update(apply=0, begin=0)
        sim.step(1)
        iterations = sim.solver_stats.iterations
        assert iterations > 0 and counts["begin"] >= 2, (iterations, counts)
        assert counts["apply"] == iterations + counts["begin"] - 1, (iterations, counts)
    sim.close()


# ----------------------------------------------------------------------------- choice


def test_auto_picks_multigrid_from_the_crossover(monkeypatch):
    """"auto" is multigrid from solvers.MULTIGRID_FROM free particles on (its finest level
    in f32 for the linearised step of an f64 run without self-collision pairs in its
    solve, else f64), block-Jacobi below; the Simulation reports the one picked, and a name is taken as given."""
    from massspring import solvers

    model = ms.load_scene("cloth").with_params(resolution=12).model()
    free = int(model.free_mask().sum())
    for threshold, precision, integrator, expected in (
            (free, "f64", "implicit", "multigrid-f32"), (free, "f32", "implicit", "multigrid"),
            (free, "f64", "bdf2", "multigrid"), (free + 1, "f64", "implicit", "block-jacobi")):
        monkeypatch.setattr(solvers, "MULTIGRID_FROM", threshold)
        sim = ms.Simulation(model, integrator=integrator, dt=DT, precision=precision)
        assert sim.preconditioner == expected and sim.info()["preconditioner"] == expected
        sim.close()
    sheets = ms.load_scene("sheets")
    monkeypatch.setattr(solvers, "MULTIGRID_FROM", 1)
    for integrator, expected in (("implicit", "multigrid"), ("backward-euler", "multigrid")):
        sim = sheets.simulation(integrator=integrator)
        assert sim.preconditioner == expected, integrator
        sim.close()
    sim = ms.Simulation(model, dt=DT, preconditioner="multigrid")
    assert sim.preconditioner == "multigrid"
    sim.close()
    with pytest.raises(ValueError, match="preconditioner"):
        ms.Simulation(model, dt=DT, preconditioner="amg")
