"""Implicit midpoint solved by Newton's method (massspring/integrators/midpoint.py).

References: the midpoint equations M (v1 - v0) = dt f((x0 + x1)/2, (v0 + v1)/2),
x1 = x0 + dt (v0 + v1)/2 with an independent numpy force (conftest.numpy_forces); the
order of accuracy against an RK4 run at a far smaller dt; the energy of an undamped
chain of zero-length springs (a linear system: midpoint conserves its quadratic energy).
"""

import numpy as np
import pytest

import massspring as ms
from massspring.scene import load_scene
from conftest import FULL, numpy_forces, one_line_error, predicted, random_system


def test_one_step_solves_the_midpoint_equations():
    """Pins, damping, drag and wind; compressed and stretched springs."""
    model = random_system(0, rest=(0.7, 1.3), drag=0.3, wind=(0.5, -0.2, 0.1))
    dt = 0.02
    sim = ms.Simulation(model, "midpoint", dt=dt, newton_tol=1e-12, cg_tol=1e-12, newton_max_iter=200)
    x0, v0 = model.positions, model.velocities
    sim.step()
    x1, v1 = sim.positions, sim.velocities
    assert np.allclose(x1, x0 + dt * (v0 + v1) / 2, rtol=0, atol=1e-14)
    free = model.free_mask()
    forces = numpy_forces(model, (x0 + x1) / 2, (v0 + v1) / 2, damping_at=predicted(model, x0, v0, dt / 2))
    residual = model.masses[:, None] * (v1 - v0) - dt * forces
    assert np.linalg.norm(residual[free]) <= 1e-9 * np.linalg.norm(dt * numpy_forces(model, x0, v0)[free])
    assert np.array_equal(v1[model.fixed], model.pin_velocity)
    assert sim.solver_stats.converged and sim.info()["newton"]


@FULL
def test_second_order_against_rk4():
    """The damped chain under gravity (nonlinear springs) over 0.1 s: the error against an
    RK4 run at dt / 50 falls by 4 per halving of dt."""
    duration = 0.1
    scene = load_scene("chain").with_params(count=10)
    reference = scene.simulation("rk4", dt=duration / 20000).step(20000).positions
    errors = []
    for n in (100, 200, 400):
        sim = scene.simulation("midpoint", dt=duration / n, newton_tol=1e-10, cg_tol=1e-12, newton_max_iter=100)
        errors.append(np.abs(sim.step(n).positions - reference).max())
        sim.close()
    orders = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert np.all((orders >= 1.8) & (orders <= 2.2)), (errors, orders)


def zero_length_chain(n=8):
    """Particles on a line joined by springs of rest length 0, the first pinned, no gravity
    and no damping: f = -K x is linear and the energy 1/2 v^T M v + 1/2 x^T K x quadratic."""
    rng = np.random.default_rng(5)
    x = np.column_stack([np.arange(n, dtype=float), np.zeros(n), np.zeros(n)])
    v = rng.normal(size=(n, 3))
    v[0] = 0.0
    springs = np.column_stack([np.arange(n - 1), np.arange(1, n)])
    return ms.Model(x, springs, masses=rng.uniform(0.5, 2.0, n), stiffness=rng.uniform(50.0, 200.0, n - 1),
                    damping=0.0, rest_lengths=0.0, velocities=v, gravity=(0.0, 0.0, 0.0), fixed=[0])


@FULL
def test_energy_of_a_linear_system_is_conserved():
    """1,000 steps of 0.02 s (about an eighth of the fastest period, 2 pi / 40 s): the
    relative energy drift stays below 1e-10 at tight solver tolerances."""
    model = zero_length_chain()
    sim = ms.Simulation(model, "midpoint", dt=0.02, newton_tol=1e-13, cg_tol=1e-14, newton_max_iter=50)
    e0 = sim.energy()["total"]
    drift = 0.0
    for _ in range(10):
        sim.step(100)
        drift = max(drift, abs(sim.energy()["total"] - e0) / e0)
    assert sim.steps == 1000 and sim.cg_failures == 0
    assert drift < 1e-10, drift


@pytest.mark.parametrize("kwargs, word", [({"newton_tol": 0.0}, "newton_tol"), ({"newton_tol": 1.5}, "newton_tol"),
                                          ({"newton_max_iter": 0}, "newton_max_iter"),
                                          ({"cg_tol": 2.0}, "cg_tol"), ({"preconditioner": "ilu"}, "preconditioner")])
def test_bad_options_are_refused_by_name(kwargs, word):
    with pytest.raises(ValueError, match=word):
        ms.Simulation(random_system(2), "midpoint", **kwargs)


def test_cli_midpoint_and_its_bad_options(capsys):
    from massspring.cli import main

    assert main(["run", "chain", "--set", "count=6", "--integrator", "midpoint", "--steps", "3",
                 "--newton-tol", "1e-6", "--quiet"]) == 0
    assert "Newton " in capsys.readouterr().out
    assert main(["run", "chain", "--integrator", "midpoint", "--newton-tol", "1.5", "--quiet"]) == 2
    one_line_error(capsys, "--newton-tol")
    assert main(["run", "chain", "--integrator", "midpoint", "--dt", "-1", "--quiet"]) == 2
    one_line_error(capsys, "--dt")
