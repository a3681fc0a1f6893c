"""One step of each integrator against an independent dense numpy evaluation.

The implicit step is compared with the dense 3n x 3n system of seed Eq. 15,

    (M - dt D - dt^2 K) v' = M v + dt f - dt D v,    x' = x + dt v',

assembled block by block from Eq. 1-3 and 13-14 (typos fixed), with the fixed
particles' rows and columns dropped and solved by ``np.linalg.solve``. Nothing here
uses the package's kernels or its algebraic shortcuts (the right-hand side keeps
the -dt D v term instead of cancelling it against the damping force).

"""

import numpy as np
import pytest

import massspring as ms
from massspring.integrators import taken
from conftest import PATHS, dense_step, dense_system, free_dofs, numpy_forces, random_system, simulation

DT = 2e-2
CG_TOL = 1e-10


def implicit_reference(model, definiteness_fix):
    A, b = dense_system(model, DT, definiteness_fix)
    v_free = np.linalg.solve(A, b)
    v = np.zeros(3 * model.n_particles)
    v[free_dofs(model)] = v_free
    v = v.reshape(-1, 3)
    return A, b, v, model.positions + DT * v


def check_implicit_step(model, definiteness_fix, path="serial"):
    A, b, v_ref, x_ref = implicit_reference(model, definiteness_fix)
    # the comparison is meaningful only on an SPD system (CG's domain)
    np.testing.assert_allclose(A, A.T, rtol=0, atol=1e-14 * np.abs(A).max())
    assert np.linalg.eigvalsh(A).min() > 0

    sim = simulation(model, path, integrator="implicit", dt=DT, cg_tol=CG_TOL, definiteness_fix=definiteness_fix)
    sim.step()
    stats = sim.solver_stats
    assert stats.converged and stats.reason == "converged", stats
    assert stats.residual <= CG_TOL
    assert sim.cg_iterations == [stats.iterations] and stats.iterations >= 1
    v, x = sim.velocities, sim.positions
    keep = free_dofs(model)

    # (1) v' satisfies the independently assembled Eq. 15 to the CG tolerance, relative
    # to the residual of the warm start v_n (the right-hand side of the velocity-change
    # form). The residual is evaluated here in f64 with the dense A; its round-off,
    # about eps ||A|| ||v'||, is added to the bound (tiny: A is diagonally dominated
    # by M for these dt and ks).
    vf = v.reshape(-1)[keep]
    first = np.linalg.norm(b - A @ model.velocities.reshape(-1)[keep])
    assert stats.first_residual == pytest.approx(first, rel=1e-9)
    roundoff = 64 * np.finfo(float).eps * np.linalg.norm(A, 2) * np.linalg.norm(vf)
    assert np.linalg.norm(b - A @ vf) <= CG_TOL * first + roundoff, (np.linalg.norm(b - A @ vf), first)
    residual, roundoff = np.linalg.norm(b - A @ vf) / np.linalg.norm(b), roundoff / np.linalg.norm(b)

    # (2) hence v' is close to the direct solution: ||v' - v*|| / ||v*|| <=
    # cond_2(A) * ||b - A v'|| / ||b|| (standard perturbation bound for A e = r),
    # with the direct solve's own error (cond eps) covered by the roundoff term.
    # The bound uses the measured residual, not a looser constant, and cond(A) is
    # computed, not guessed (it is about 2-5 here: M dominates, so the bound is tight).
    cond = np.linalg.cond(A)
    vref = v_ref.reshape(-1)[keep]
    err = np.linalg.norm(vf - vref) / np.linalg.norm(vref)
    assert err <= cond * (residual + roundoff), (err, cond, residual)

    # (3) x' = x + dt v' to round-off, and so x' is as close to x* as dt v' is to dt v*
    scale = np.abs(model.positions).max() + DT * np.abs(v).max()
    np.testing.assert_allclose(x, model.positions + DT * v, rtol=0, atol=4 * np.finfo(float).eps * scale)
    np.testing.assert_allclose(x, x_ref, rtol=0, atol=DT * cond * (residual + roundoff) * np.linalg.norm(vref)
                               + 4 * np.finfo(float).eps * scale)

    # (4) fixed particles: zero velocity and unchanged position, exactly
    fixed = model.fixed
    assert np.all(v[fixed] == 0) and np.all(x[fixed] == model.positions[fixed])
    return sim


def has_compressed(model, factor=1.0):
    length = np.linalg.norm(model.positions[model.springs[:, 1]] - model.positions[model.springs[:, 0]], axis=1)
    return np.any(model.rest_lengths > factor * length)


@pytest.mark.fast_sample(path=["serial"])
@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("seed", range(4))
def test_implicit_step_matches_dense_solve_with_fix(seed, path):
    model = random_system(seed)
    assert has_compressed(model), "the system should contain compressed springs (fix active)"
    # the fix changes the matrix for this system, so the test distinguishes fix/no fix
    A_fix, _ = dense_system(model, DT, True)
    A_raw, _ = dense_system(model, DT, False)
    assert np.abs(A_fix - A_raw).max() > 1e-6
    sim = check_implicit_step(model, definiteness_fix=True, path=path)
    assert_far_from_other_variant(sim, model, definiteness_fix=True)


@pytest.mark.fast_sample(path=["serial"])
@pytest.mark.parametrize("path", PATHS)
def test_coincident_zero_rest_length_springs_are_stiff_in_the_solve(path):
    """A zero-rest-length spring is linear, f_i = ks (x_j - x_i): K_ii = -ks I also
    when its ends coincide and it has no direction. Particles 0-2 start at one point
    with different velocities, tied by l0 = 0 springs (and 2 to the fixed 3 by one of
    l0 = 0.5): the step matches the dense solve with those -ks I blocks, and is far
    from the step a solve without them would give (the pair moving apart freely)."""
    x = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.5]])
    v = np.array([[0.3, 0.0, 0.0], [-0.2, 0.1, 0.0], [0.0, 0.0, 0.4], [0.0, 0.0, 0.0]])
    model = ms.Model(x, [[0, 1], [1, 2], [2, 3]], masses=0.1, stiffness=[400.0, 300.0, 200.0],
                     damping=0.2, rest_lengths=[0.0, 0.0, 0.5], velocities=v, fixed=[3])
    sim = check_implicit_step(model, definiteness_fix=True, path=path)
    free_flight = v[:3] + DT * model.gravity  # what the step was before: no stiffness at coincidence
    assert np.linalg.norm(sim.velocities[:3] - free_flight) > 0.1 * np.linalg.norm(free_flight)


def assert_far_from_other_variant(sim, model, definiteness_fix):
    """The step is much closer to its own reference than the two references are to
    each other: the comparison can tell the fixed from the unfixed matrix."""
    _, _, v_own, _ = implicit_reference(model, definiteness_fix)
    _, _, v_other, _ = implicit_reference(model, not definiteness_fix)
    gap = np.linalg.norm(v_own - v_other)
    assert gap > 1e-4 * np.linalg.norm(v_own)
    assert np.linalg.norm(sim.velocities - v_own) < 1e-3 * gap


@pytest.mark.fast_sample(path=["serial"])
@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("seed", range(2))
def test_implicit_step_matches_dense_solve_without_fix_stretched(seed, path):
    """Stretched springs only (l0 < l): Eq. 13 as written is SPD-compatible."""
    model = random_system(100 + seed, rest=(0.5, 0.95))
    assert not has_compressed(model)
    check_implicit_step(model, definiteness_fix=False, path=path)


@pytest.mark.fast_sample(path=["serial"])
@pytest.mark.parametrize("path", PATHS)
def test_implicit_step_matches_dense_solve_without_fix_mildly_compressed(path):
    """Mildly compressed springs, small enough that M keeps Eq. 13's matrix SPD: the
    unclamped transverse term is used (this matrix differs from the fixed one)."""
    model = random_system(200, rest=(0.9, 1.2))
    assert has_compressed(model)
    A_fix, _ = dense_system(model, DT, True)
    A_raw, _ = dense_system(model, DT, False)
    assert np.abs(A_fix - A_raw).max() > 1e-6
    sim = check_implicit_step(model, definiteness_fix=False, path=path)
    assert_far_from_other_variant(sim, model, definiteness_fix=False)


@pytest.mark.fast_sample(path=["serial"])
@pytest.mark.parametrize("path", PATHS)
def test_implicit_several_steps_match_dense_solves(path):
    """Three steps: each step's state is the previous step's output (warm start from
    v_n, positions and Jacobians updated)."""
    model = random_system(300)
    sim = simulation(model, path, integrator="implicit", dt=DT, cg_tol=CG_TOL)
    x, v = model.positions.copy(), model.velocities.copy()
    keep = free_dofs(model)
    for _ in range(3):
        A, b = dense_system(model, DT, True, x=x, v=v)
        v = np.zeros_like(v)
        v.reshape(-1)[keep] = np.linalg.solve(A, b)
        x = x + DT * v
        sim.step()
        stats = sim.solver_stats
        assert stats.converged and stats.residual <= CG_TOL
        # relative 2-norm error <= cond(A) * relative residual (see check_implicit_step),
        # with 1e-13 for round-off in both solutions
        bound = np.linalg.cond(A) * (CG_TOL + 1e-13) * np.linalg.norm(v)
        assert np.linalg.norm(sim.velocities - v) <= bound
        assert np.linalg.norm(sim.positions - x) <= DT * bound + 1e-14
        x, v = sim.positions, sim.velocities  # continue from the simulated state


@pytest.mark.fast_sample(integrator=["symplectic"], path=["serial"])
@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("integrator", ["explicit", "symplectic"])
@pytest.mark.parametrize("seed", range(3))
def test_euler_step_matches_numpy(integrator, seed, path):
    """explicit: x' = x + dt v, v' = v + dt f(x, v)/m; symplectic: x' = x + dt v'.
    Both are a few f64 operations per particle, so they agree to round-off: the sum
    of a particle's force terms (in another order than here) is exact to within
    (number of terms) eps times the sum of their magnitudes, at most ~8 terms here,
    and the update adds a few roundings; 16 eps times the scale covers both."""
    model = random_system(seed)
    x, v = model.positions, model.velocities
    f, mag = numpy_forces(model, x, v, magnitude=True)
    free = model.free_mask()
    v_new = v + DT * f / model.masses[:, None]
    v_new[~free] = 0.0
    x_new = x + DT * (v_new if integrator == "symplectic" else v)
    x_new[~free] = x[~free]

    sim = simulation(model, path, integrator=integrator, dt=DT)
    sim.step()
    eps = np.finfo(float).eps
    assert np.bincount(model.springs.ravel()).max() <= 8
    v_scale = np.abs(v).max() + DT * (mag / model.masses).max()
    np.testing.assert_allclose(sim.velocities, v_new, rtol=0, atol=16 * eps * v_scale)
    np.testing.assert_allclose(sim.positions, x_new, rtol=0, atol=16 * eps * (np.abs(x).max() + DT * v_scale))
    assert np.all(sim.velocities[~free] == 0) and np.all(sim.positions[~free] == x[~free])
    # the forces matter: the change of v is far above the tolerance
    assert np.abs(v_new - v).max() > 1e6 * 16 * eps * v_scale


@pytest.mark.fast_sample(integrator=["implicit"])
@pytest.mark.parametrize("integrator", ["explicit", "symplectic", "implicit"])
def test_serial_and_parallel_drivers_agree(integrator):
    """Both drivers run the same algorithm on the same data: over 10 steps of a
    random system they agree to round-off (they may sum in different orders; the
    state is O(1), so 1e-12 is a few hundred eps of accumulated difference, while
    the step's own change is O(dt))."""
    model = random_system(400)
    out = []
    for path in PATHS:
        sim = simulation(model, path, integrator=integrator, dt=DT, **taken(integrator, {"cg_tol": 1e-12}))
        sim.step(3)  # multi-step calls of odd and even length
        sim.step(7)
        sim.step(0)
        out.append((sim.positions, sim.velocities, list(sim.cg_iterations)))
        assert sim.steps == 10
    np.testing.assert_allclose(out[0][0], out[1][0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(out[0][1], out[1][1], rtol=0, atol=1e-11)
    if integrator == "implicit":
        assert len(out[0][2]) == 10 and all(it > 0 for it in out[0][2])
        assert all(abs(a - b) <= 1 for a, b in zip(out[0][2], out[1][2])), out


@pytest.mark.fast_sample(integrator=["symplectic"], path=["serial"])
@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("integrator", ["explicit", "symplectic"])
def test_multi_step_call_equals_single_steps(integrator, path):
    """step(n) in one call (one launch for the serial driver, ping-ponging buffers)
    gives exactly the state of n calls of step(1), for odd and even n."""
    model = random_system(401)
    a = simulation(model, path, integrator=integrator, dt=DT)
    b = simulation(model, path, integrator=integrator, dt=DT)
    for n in (3, 4, 1):
        a.step(n)
        for _ in range(n):
            b.step()
        np.testing.assert_array_equal(a.positions, b.positions)
        np.testing.assert_array_equal(a.velocities, b.velocities)
    assert a.steps == b.steps == 8


# ----------------------------------------------------------------------------- pins and air


def moving_pins_system(seed, drag=0.0, wind=(0.0, 0.0, 0.0)):
    """A random system whose 2 pins move with random velocities (and optional air drag)."""
    rng = np.random.default_rng(1000 + seed)
    return random_system(seed, n_fixed=2, pin_velocity=rng.normal(size=(2, 3)), drag=drag, wind=wind)


@pytest.mark.fast_sample(path=["serial"])
@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("seed", range(3))
def test_implicit_step_with_moving_pins_matches_dense_solve(seed, path):
    """Kinematic pins: Eq. 15 on the free particles with the pins' velocities prescribed,
    their columns of A moved to the right-hand side (A_ff v_f = b_f - A_fp v_p), solved
    densely. The pins' velocity is their pin velocity and they move by dt times it."""
    model = moving_pins_system(seed)
    assert model.has_moving_pins and np.all(model.velocities[model.fixed] == model.pin_velocity)
    v_ref = dense_step(model, DT, True)
    A, b = dense_system(model, DT, True)
    sim = simulation(model, path, integrator="implicit", dt=DT, cg_tol=CG_TOL)
    sim.step()
    assert sim.solver_stats.converged, sim.solver_stats
    v = sim.velocities
    bound = np.linalg.cond(A) * (CG_TOL + 1e-13) * np.linalg.norm(v_ref)
    assert np.linalg.norm(v - v_ref) <= bound
    np.testing.assert_array_equal(v[model.fixed], model.pin_velocity)
    np.testing.assert_allclose(sim.positions[model.fixed], model.positions[model.fixed] + DT * model.pin_velocity,
                               rtol=0, atol=4 * np.finfo(float).eps)
    # the pins' velocities matter: the solve with fixed pins is far from this one
    still = ms.Model(model.positions, model.springs, masses=model.masses, stiffness=model.stiffness,
                     damping=model.damping, rest_lengths=model.rest_lengths, velocities=model.velocities,
                     gravity=model.gravity, fixed=model.fixed)
    assert np.linalg.norm(dense_step(still, DT, True) - v_ref) > 1e3 * bound


@pytest.mark.fast_sample(path=["serial"])
@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("seed", range(2))
def test_implicit_step_with_drag_and_wind_matches_dense_solve(seed, path):
    """Air drag -drag (v - wind) enters D as -drag I and f - D v as drag * wind."""
    model = moving_pins_system(seed, drag=3.0, wind=(2.0, -1.0, 0.5))
    v_ref = dense_step(model, DT, True)
    A, _ = dense_system(model, DT, True)
    sim = simulation(model, path, integrator="implicit", dt=DT, cg_tol=CG_TOL)
    sim.step()
    assert sim.solver_stats.converged and "drag" in sim.info()["terms"]
    bound = np.linalg.cond(A) * (CG_TOL + 1e-13) * np.linalg.norm(v_ref)
    assert np.linalg.norm(sim.velocities - v_ref) <= bound
    calm = moving_pins_system(seed)  # the same system without air: far away
    assert np.linalg.norm(dense_step(calm, DT, True) - v_ref) > 1e3 * bound


@pytest.mark.fast_sample(integrator=["symplectic"])
@pytest.mark.parametrize("integrator", ["explicit", "symplectic"])
def test_euler_step_with_drag_and_moving_pins_matches_numpy(integrator):
    """One explicit/symplectic step with drag, wind and moving pins, against numpy."""
    model = moving_pins_system(5, drag=3.0, wind=(2.0, -1.0, 0.5))
    x, v = model.positions, model.velocities
    free = model.free_mask()
    v_new = v + DT * numpy_forces(model, x, v) / model.masses[:, None]
    v_new[~free] = v[~free]
    x_new = x + DT * (v_new if integrator == "symplectic" else v)
    x_new[~free] = x[~free] + DT * model.pin_velocity
    sim = simulation(model, "serial", integrator=integrator, dt=DT)
    sim.step()
    np.testing.assert_allclose(sim.velocities, v_new, rtol=0, atol=1e-13)
    np.testing.assert_allclose(sim.positions, x_new, rtol=0, atol=1e-14)
