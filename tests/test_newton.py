"""Backward Euler, BDF2 and implicit midpoint solved by Newton's method (massspring/integrators/newton.py).

References: the backward-Euler equations M (v1 - v0) = dt f(x0 + dt v1, v1) with an
independent numpy force (conftest.numpy_forces; spring damping along the directions at
x0 + dt v0, conftest.predicted); the order of accuracy against an RK4
run at a far smaller dt; the terminal velocity m g / c + wind of a particle with
linear drag; a cloth resting on a plane; the energy of the undamped stiff chain.
"""

import math

import numpy as np
import pytest

import massspring as ms
from massspring.integrators import INTEGRATORS
from massspring.integrators import newton as newton_integrators
from massspring.scene import load_scene
from conftest import FULL, PATHS, numpy_forces, predicted, random_system, simulation

NEWTON = tuple(name for name, cls in INTEGRATORS.items() if cls.traits.newton)


def free_rows(model):
    return model.free_mask()


@pytest.mark.fast_sample(path=["serial"])
@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("seed", [0, 1])
def test_one_step_solves_the_backward_euler_equations(seed, path):
    """Pins, damping, drag and wind; compressed and stretched springs; the definiteness fix on."""
    model = random_system(seed, rest=(0.7, 1.3), drag=0.3, wind=(0.5, -0.2, 0.1))
    dt = 0.02
    sim = simulation(model, path, integrator="backward-euler", dt=dt, newton_tol=1e-12, cg_tol=1e-12,
                     newton_max_iter=200)
    x0, v0 = model.positions, model.velocities
    sim.step()
    x1, v1 = sim.positions, sim.velocities
    assert np.allclose(x1, x0 + dt * v1, rtol=0, atol=1e-14)
    forces = numpy_forces(model, x1, v1, damping_at=predicted(model, x0, v0, dt))
    residual = model.masses[:, None] * (v1 - v0) - dt * forces
    scale = np.linalg.norm(dt * numpy_forces(model, x0, v0)[free_rows(model)])
    assert np.linalg.norm(residual[free_rows(model)]) <= 1e-9 * scale
    assert np.array_equal(v1[model.fixed], model.pin_velocity)
    stats = sim.solver_stats
    assert stats.converged and stats.newton_iterations >= 2 and len(stats.cg_per_newton) == stats.newton_iterations


@FULL
@pytest.mark.parametrize("options", [{}, {"newton_tol": 1e-10, "newton_max_iter": 200}])
def test_the_linearised_step_leaves_the_equations_unsolved_where_newton_solves_them(options):
    """A stretched, moving stiff chain: Eq. 15 (one linearisation) misses the backward-Euler
    equations by a large fraction of dt f; Newton meets them to 1e-6, at its default
    settings too (where loose inner solves, kept after a line search had cut a step,
    left 2.3e-4 after all 50 iterations)."""
    scene = load_scene("stiffchain")
    model = scene.model()
    rng = np.random.default_rng(4)
    x = model.positions * 1.02 + rng.normal(scale=1e-3, size=model.positions.shape)
    v = rng.normal(scale=0.5, size=x.shape)
    x[model.fixed] = model.positions[model.fixed]
    v[model.fixed] = 0.0
    dt = 0.01
    scale = np.linalg.norm((dt * numpy_forces(model, x, v))[free_rows(model)])
    misses = {}
    for integrator, kwargs in (("implicit", {}), ("backward-euler", options)):
        sim = ms.Simulation(model, integrator, dt=dt, **kwargs).set_state(x, v)
        sim.step()
        x1, v1 = sim.positions, sim.velocities
        residual = model.masses[:, None] * (v1 - v) - dt * numpy_forces(model, x1, v1)
        misses[integrator] = np.linalg.norm(residual[free_rows(model)]) / scale
    assert misses["implicit"] > 1e-2
    assert misses["backward-euler"] <= 1e-6


@FULL
@pytest.mark.parametrize("damped", [False, True])
def test_newton_converges_quadratically_without_the_fix(damped):
    """No definiteness fix: the operator is the exact Jacobian (spring damping too: it acts
    along the directions at the step's prediction, linear in v), so near the solution each
    residual is at most a power 1.5 of the one before (relative residuals)."""
    base = random_system(0, rest=(0.8, 0.95))
    model = ms.Model(base.positions, base.springs, masses=base.masses, stiffness=base.stiffness,
                     rest_lengths=base.rest_lengths, velocities=base.velocities, gravity=base.gravity,
                     fixed=base.fixed, damping=base.damping if damped else 0.0)
    sim = ms.Simulation(model, "backward-euler", dt=0.05, cg_tol=1e-14, newton_tol=1e-13, newton_max_iter=30,
                        definiteness_fix=False)
    sim.step()
    residuals = np.array(sim.solver_stats.newton_residuals)
    assert residuals[0] == 1.0 and residuals[-1] < 1e-10
    pairs = [(a, b) for a, b in zip(residuals[:-1], residuals[1:]) if 1e-10 < a < 1e-1 and b > 1e-12]
    assert len(pairs) >= 2
    for a, b in pairs:
        assert b <= a**1.5, residuals


@pytest.mark.fast_sample(integrator=["backward-euler"])
@pytest.mark.parametrize("integrator", NEWTON)
def test_overwhelming_damping_at_a_huge_step_does_not_run_away(integrator):
    """The cloth with spring damping 1e9 N s/m at dt 1 s: with the damping's direction taken
    along the iterate, Newton's line search decreased a merit that was not (*)'s potential
    and the state ran away (kinetic energy 6e8 J on this 8 x 8 cloth with backward Euler
    and BDF2, 4e26 J with midpoint); along the step's prediction it is, and every
    iteration decreases it. Backward Euler's and BDF2's total energy falls; midpoint's does
    not (not L-stable, it flips the velocities of modes damped far faster than dt instead
    of damping them, and its spring energy grows at a step this far outside its accuracy:
    docs/model.md), but its kinetic energy stays below the gravity's work."""
    scene = load_scene("cloth").with_params(resolution=8).with_settings(["damping=1e9"])
    sim = scene.simulation(integrator, dt=1.0)
    energy = start = sim.energy()["total"]
    for _ in range(2):
        sim.step()
        if integrator == "midpoint":
            assert sim.energy()["kinetic"] <= start - sim.energy()["gravity"]
        else:
            assert sim.energy()["total"] <= energy
        energy = sim.energy()["total"]


@FULL
@pytest.mark.parametrize("integrator", NEWTON)
def test_newton_converges_on_a_heavily_damped_cloth(integrator):
    """The shipped cloth with ten times its spring damping (20 N s/m), 20 steps at dt 1/60:
    every step meets newton_tol within the default 50 iterations (14 of 20 backward-Euler
    steps missed it while the damping's direction turned with the iterate)."""
    sim = load_scene("cloth").with_settings(["damping=20"]).simulation(integrator, dt=1 / 60)
    for _ in range(20):
        sim.step()
        assert sim.solver_stats.converged, sim.solver_stats


def _chain_errors(integrator, counts, duration=0.1):
    scene = load_scene("chain").with_params(count=10)
    reference = scene.simulation("rk4", dt=duration / 20000).step(20000).positions
    errors = []
    for n in counts:
        sim = scene.simulation(integrator, dt=duration / n, newton_tol=1e-10, cg_tol=1e-12, newton_max_iter=100)
        sim.step(n)
        errors.append(np.abs(sim.positions - reference).max())
        sim.close()
    return np.array(errors)


@FULL
@pytest.mark.parametrize("integrator, low, high", [("backward-euler", 0.9, 1.1), ("bdf2", 1.8, 2.2)])
def test_order_of_accuracy_against_rk4(integrator, low, high):
    errors = _chain_errors(integrator, (100, 200, 400))
    orders = np.log2(errors[:-1] / errors[1:])
    assert np.all((orders >= low) & (orders <= high)), (errors, orders)


@FULL
@pytest.mark.parametrize("integrator", ["implicit", *NEWTON])
def test_terminal_velocity_with_drag_at_default_tolerances(integrator):
    """v -> m g / c + wind; the step's solve is relative to its own change, so a steady
    motion is solved as closely as a fast one."""
    m, c, g, wind = 0.2, 0.5, np.array([0.0, 0.0, -9.81]), np.array([1.0, -0.5, 0.0])
    model = ms.Model([[0.0, 0.0, 0.0]], np.zeros((0, 2), int), masses=m, gravity=g, drag=c, wind=wind)
    sim = ms.Simulation(model, integrator, dt=0.05)
    sim.step(600)  # 30 s: 75 time constants m / c
    terminal = m * g / c + wind
    assert np.linalg.norm(sim.velocities[0] - terminal) <= 1e-8 * np.linalg.norm(terminal)


@FULL
@pytest.mark.parametrize("integrator", NEWTON)
def test_a_cloth_resting_on_a_plane_stays_at_rest(integrator):
    """Contacts and friction inside Newton: a flat cloth at rest on the ground, no pins."""
    base = load_scene("cloth").with_params(resolution=6).model()
    x = base.positions.copy()
    x[:, 2] = 0.0
    model = ms.Model(x, base.springs, masses=base.masses, stiffness=base.stiffness, damping=base.damping,
                     rest_lengths=np.linalg.norm(x[base.springs[:, 1]] - x[base.springs[:, 0]], axis=1),
                     gravity=base.gravity, colliders=[ms.Plane((0, 0, 0), (0, 0, 1), friction=0.5)])
    sim = ms.Simulation(model, integrator, dt=1 / 60)
    for _ in range(60):
        sim.step()
        assert np.abs(sim.positions - x).max() <= 1e-9
    assert np.abs(sim.velocities).max() <= 1e-9
    assert sim.cg_failures == 0


@pytest.mark.fast_sample(dt=[0.01])
@pytest.mark.parametrize("dt", [0.01, 0.002])
def test_stiff_chain_energy_never_grows_with_backward_euler(dt):
    """The shipped undamped stiff chain over 2 s: total energy never above its start
    (the linearised step gains up to 15 J here, see test_stability)."""
    sim = load_scene("stiffchain").simulation("backward-euler", dt=dt)
    e0 = sim.energy()["total"]
    for _ in range(int(round(2.0 / dt))):
        sim.step()
        assert sim.energy()["total"] <= e0 + 1e-9
    assert sim.cg_failures == 0


@FULL
@pytest.mark.parametrize("path", PATHS)
def test_bdf2_restart_continues_bitwise(path):
    model = random_system(3)
    whole = simulation(model, path, integrator="bdf2", dt=2e-3).step(12)
    part = simulation(model, path, integrator="bdf2", dt=2e-3).step(5)
    x, v, carried = part.positions, part.velocities, part.carried_state()
    assert set(carried) == {"x_prev", "v_prev", "ready"} and carried["ready"].all()
    part.close()
    rest = simulation(model, path, integrator="bdf2", dt=2e-3).set_state(x, v, steps=5, carried=carried).step(7)
    assert np.array_equal(rest.positions, whole.positions) and np.array_equal(rest.velocities, whole.velocities)
    cold = simulation(model, path, integrator="bdf2", dt=2e-3).set_state(x, v, steps=5).step(7)
    assert not np.array_equal(cold.positions, whole.positions)  # without its history it restarts with backward Euler


def one_launch_cases():
    """(id, model, integrator, options, steps): the stiff chain with BDF2, whose line
    searches cut steps; a random system falling onto a plane with friction (contacts held
    through the iterations, friction after them) and drag and wind, with midpoint; with
    backward Euler stopped by Newton's limit; with BDF2 in f32. (Each case compiles the
    one-launch kernel for its own configuration: a few seconds each.)"""
    chain = load_scene("stiffchain").model()
    falling = random_system(5, drag=0.3, wind=(0.5, -0.2, 0.1), n_fixed=0,
                            colliders=[ms.Plane((0.0, 0.0, -1.05), (0.0, 0.0, 1.0), friction=0.5)])
    return [("stiffchain-bdf2", chain, "bdf2", {"dt": 0.01}, 12),
            ("falling-midpoint", falling, "midpoint", {"dt": 5e-3}, 48),
            ("falling-limit", falling, "backward-euler", {"dt": 5e-3, "newton_max_iter": 2}, 48),
            ("falling-f32", falling, "bdf2", {"dt": 5e-3, "precision": "f32"}, 48)]


@FULL  # each case compiles the one-launch kernel: seconds
@pytest.mark.parametrize("case", [c[0] for c in one_launch_cases()])
def test_newton_in_one_launch_equals_the_loop_driven_from_python(case, monkeypatch):
    """On a small system Newton's whole iteration runs in one launch (``newton_solve``) once a
    run has made ``ONE_LAUNCH_AFTER`` tries (here from the first; the stiff chain's BDF2 from
    its fourth, switching mid-run); the same serial kernels driven phase by phase from Python
    give the same bits and the same solver record (CG iterations of each solve, ||g|| of
    each iterate, cuts, reason)."""
    _, model, integrator, options, steps = next(c for c in one_launch_cases() if c[0] == case)
    monkeypatch.setattr(newton_integrators, "ONE_LAUNCH_AFTER", 4 if case == "stiffchain-bdf2" else 0)
    runs = []
    for one in (True, False):
        if not one:
            monkeypatch.setattr(INTEGRATORS[integrator], "one_launch", lambda self: False)
        sim = simulation(model, "serial", integrator=integrator, **options)
        records, lowest = [], math.inf
        for _ in range(steps):
            sim.step()
            records.append(sim.solver_stats)
            lowest = min(lowest, sim.positions[:, 2].min())
        assert sim.stepper.one_launch() is one
        runs.append((sim.positions, sim.velocities, records, lowest))
    assert np.array_equal(runs[0][0], runs[1][0]) and np.array_equal(runs[0][1], runs[1][1])
    assert runs[0][2] == runs[1][2]
    records = runs[0][2]
    if case.startswith("stiffchain"):
        assert sum(r.cuts for r in records) > 0
    if case == "falling-limit":
        assert any(r.reason == "max_newton" for r in records)
    if case.startswith("falling"):
        assert np.isclose(runs[0][3], -1.05, atol=1e-5)  # a particle has been on the plane


def test_a_short_run_keeps_the_loop_driven_from_python():
    """The one-launch kernel costs about 2 s more to compile: a run takes it only after
    ``ONE_LAUNCH_AFTER`` tries, or when a run before it compiled it for its bundle."""
    sim = simulation(random_system(7), "serial", integrator="backward-euler", dt=1e-3)
    sim.step(3)
    assert sim.stepper.tries == 3
    if ("newton_solve", sim.stepper.cfg) not in sim.stepper.dev.compiled:
        assert not sim.stepper.one_launch()
    sim.stepper.tries = newton_integrators.ONE_LAUNCH_AFTER
    assert sim.stepper.one_launch()


def test_newton_options_are_validated_and_reported():
    model = random_system(2)
    for kwargs, word in (({"newton_tol": 0.0}, "newton_tol"), ({"newton_tol": 1.5}, "newton_tol"),
                         ({"newton_max_iter": 0}, "newton_max_iter"), ({"newton_max_iter": 2.5}, "newton_max_iter")):
        with pytest.raises(ValueError, match=word):
            ms.Simulation(model, "backward-euler", **kwargs)
    sim = ms.Simulation(model, "bdf2", dt=1e-2, newton_tol=1e-6, newton_max_iter=1)
    sim.step(3)
    assert sim.newton_iterations == [1, 1, 1] and sim.cg_failures == 3
    assert sim.solver_stats.reason == "max_newton" and not sim.solver_stats.converged
    info = sim.info()
    assert info["newton"] and info["preconditioner"] == "block-jacobi"
    assert math.isfinite(sim.solver_stats.newton_residual)


def test_cli_newton_options(capsys):
    """--newton-* reach the solver and its summary, are checked by name, and are refused by an
    integrator that takes no Newton iterations."""
    from massspring.cli import main
    from conftest import one_line_error

    assert main(["run", "stiffchain", "--set", "count=6", "--steps", "3", "--newton-tol", "1e-6",
                 "--newton-max-iter", "40", "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "Newton " in out and "(tol 1e-06)" in out
    assert main(["run", "spring", "--integrator", "implicit", "--newton-tol", "1e-3", "--quiet"]) == 2
    one_line_error(capsys, "--newton-tol", "takes no Newton iterations", "backward-euler, bdf2")
    assert main(["run", "stiffchain", "--newton-tol", "1.5", "--quiet"]) == 2
    one_line_error(capsys, "--newton-tol")
    assert main(["run", "stiffchain", "--newton-max-iter", "0", "--quiet"]) == 2
    one_line_error(capsys, "--newton-max-iter")


@FULL
def test_the_summary_advises_when_newton_stops_at_its_limit(capsys):
    """Issue 42: runs that reached the Newton limit said only "N step(s) not converged"."""
    from massspring.cli import main

    assert main(["run", "chain", "--integrator", "backward-euler", "--newton-max-iter", "1", "--newton-tol", "1e-14",
                 "--steps", "3", "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "note        Newton stopped at --newton-max-iter 1 before --newton-tol 1e-14 on 3 of 3 steps" in out, out
    assert "smaller --dt" in out
