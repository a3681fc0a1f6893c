"""The multigrid cycle in f32 inside the f64 CG (``preconditioner="multigrid-f32"``):
the f64 cycle rounded to f32, still symmetric positive definite to that rounding, and
solves of Eq. 15 as accurate as the f64 cycle's, with pins, contact and the
Newton-solved steps' lagged operator."""

import numpy as np
import pytest

import massspring as ms
from conftest import FULL, dense_step, free_dofs
from massspring.engine.operators import SystemOperator
from massspring.solvers import aggregation
from test_multigrid import DT, swinging_cloth


@FULL
def test_f32_cycle_is_the_f64_cycle_rounded():
    """On a swung 40^2 cloth (three levels), B32 r is B64 r to f32's precision, and not
    bit for bit (the cycle really runs in f32); and B32 is symmetric to that precision and
    positive on the free directions, so CG may take it."""
    model = swinging_cloth(40)
    assert len(aggregation.build(model, DT).levels) == 3
    wide = SystemOperator(model, DT, preconditioner="multigrid")
    narrow = SystemOperator(model, DT, preconditioner="multigrid-f32")
    keep = free_dofs(model).reshape(-1, 3)
    rng = np.random.default_rng(7)
    for _ in range(3):
        x, y = rng.normal(size=keep.shape) * keep, rng.normal(size=keep.shape) * keep
        b64, b32, c32 = wide.precondition(x), narrow.precondition(x), narrow.precondition(y)
        assert np.all(b32[~keep] == 0)
        gap = np.abs(b32 - b64).max() / np.abs(b64).max()
        assert 1e-9 < gap < 2e-6, gap  # measured 1.5e-7 to 1.7e-7
        scale = np.linalg.norm(x) * np.linalg.norm(c32)
        assert abs(np.sum(x * c32) - np.sum(y * b32)) <= 1e-7 * scale  # measured 3e-10 to 3e-9
        assert np.sum(x * b32) > 0
    wide.close()
    narrow.close()


def test_step_matches_a_dense_solve_of_eq15():
    """One implicit step of the swinging 24^2 cloth (pinned corners) solved to 1e-10 with
    the f32 cycle equals numpy's direct solve of Eq. 15 at the same state: CG's residual is
    the f64 one, whatever the cycle's precision."""
    scene = ms.load_scene("cloth").with_params(resolution=24)
    sim = scene.simulation(integrator="implicit", dt=DT, preconditioner="multigrid-f32", cg_tol=1e-10,
                           cg_max_iter=500)
    sim.step(3)
    state = scene.model().replaced(positions=sim.positions, velocities=sim.velocities)
    sim.step(1)
    assert sim.cg_failures == 0, sim.solver_stats
    reference = dense_step(state, DT, True)
    assert np.abs(sim.velocities - reference).max() <= 1e-9 * np.abs(reference).max()  # measured 7e-12
    sim.close()


@FULL
@pytest.mark.parametrize("integrator", ["implicit", "backward-euler"])
def test_contact_and_newton_steps_match_the_f64_cycle(integrator):
    """The drape landing on its sphere (contact, friction) with the linearised step, and
    the swinging cloth with backward Euler (the lagged operator): 10 steps at CG tolerance
    1e-10 with either cycle end at the same state to what that tolerance allows, and the f32
    cycle needs at most one CG iteration a step more on average."""
    scene, steps = ((ms.load_scene("drape").with_params(resolution=16), 10) if integrator == "implicit"
                    else (ms.load_scene("cloth").with_params(resolution=16), 10))
    out = {}
    for preconditioner in ("multigrid", "multigrid-f32"):
        sim = scene.simulation(integrator=integrator, dt=DT, preconditioner=preconditioner, cg_tol=1e-10,
                               cg_max_iter=500)
        sim.step(steps)
        assert sim.cg_failures == 0, (preconditioner, sim.solver_stats)
        out[preconditioner] = (sim.positions, sim.velocities, sum(sim.cg_iterations))
        sim.close()
    (x64, v64, its64), (x32, v32, its32) = out["multigrid"], out["multigrid-f32"]
    moved = np.abs(x64 - scene.model().positions).max()
    assert np.abs(x32 - x64).max() <= 1e-8 * moved  # measured 1.3e-10 (drape), 4e-11 (backward Euler)
    assert np.abs(v32 - v64).max() <= 1e-8 * np.abs(v64).max()  # measured 7e-10, 2e-10
    assert its32 <= its64 + steps, (its32, its64)


@FULL
@pytest.mark.parametrize("stiffness", [1e4, 1e6])
def test_iteration_counts_as_the_f64_cycle(stiffness):
    """At the default tolerance a 32^2 cloth's 20 steps take as many CG iterations with
    the f32 cycle as with the f64 one, give or take one a step."""
    scene = ms.load_scene("cloth").with_params(resolution=32, stiffness=stiffness)
    counts = {}
    for preconditioner in ("multigrid", "multigrid-f32"):
        sim = scene.simulation(integrator="implicit", preconditioner=preconditioner)
        sim.step(20)
        assert sim.cg_failures == 0
        counts[preconditioner] = np.array(sim.cg_iterations)
        sim.close()
    assert np.abs(counts["multigrid-f32"] - counts["multigrid"]).max() <= 1, counts


@FULL
def test_gradient_through_the_f32_cycle_matches_the_f64_one():
    """The adjoint solves run with the run's preconditioner: with the f32 cycle and CG
    to 1e-12, the implicit step's gradient is the f64 cycle's."""
    model = ms.load_scene("cloth").with_params(resolution=10).model()

    def objective(frames):
        return float(frames.positions[-1].sum()), {"positions": np.ones_like(frames.positions)}

    grads = {}
    for preconditioner in ("multigrid", "multigrid-f32"):
        _, grads[preconditioner] = ms.gradient(model, objective, ["stiffness", "damping"], steps=5,
                                               integrator="implicit", dt=DT, preconditioner=preconditioner,
                                               cg_tol=1e-12, cg_max_iter=500)
    for name in ("stiffness", "damping"):
        ref = grads["multigrid"][name]
        assert np.abs(grads["multigrid-f32"][name] - ref).max() <= 1e-8 * np.abs(ref).max()


def test_self_collision_in_the_solve_is_refused_before_any_field():
    """Self-collision pairs in the linearised solve need the f64 cycle: a ValueError naming
    the preconditioner and the way out, before the bundle is allocated."""
    scene = ms.load_scene("sheets")
    assert scene.self_collision is not None
    with pytest.raises(ValueError, match="multigrid-f32.*use preconditioner 'multigrid'"):
        scene.simulation(integrator="implicit", preconditioner="multigrid-f32")
