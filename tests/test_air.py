"""Air drag and wind: the analytic solution of a particle falling with linear drag,
the terminal velocity, and what a model without drag compiles.

One free particle of mass m under gravity g with drag f = -c (v - w) obeys
v' = g - k (v - w), k = c / m, whose exact solution is

    v(t) = v_T + (v_0 - v_T) exp(-k t),   v_T = m g / c + w (the terminal velocity),
    x(t) = x_0 + v_T t + (v_0 - v_T) (1 - exp(-k t)) / k.
"""

import math

import numpy as np
import pytest

import massspring as ms
from massspring.integrators import INTEGRATORS, taken
from conftest import PATHS, simulation

M, C = 0.5, 1.5
G = np.array([0.0, 0.0, -9.81])
WIND = np.array([3.0, -1.0, 0.5])
X0, V0 = np.array([0.2, -0.1, 1.0]), np.array([1.0, 2.0, 4.0])
ORDER = {name: cls.traits.order for name, cls in INTEGRATORS.items()}


def falling(drag=C, wind=WIND):
    return ms.Model([X0], np.zeros((0, 2), dtype=int), masses=M, velocities=[V0], gravity=G, drag=drag, wind=wind)


def exact(t):
    k = C / M
    terminal = M * G / C + WIND
    decay = math.exp(-k * t)
    return X0 + terminal * t + (V0 - terminal) * (1 - decay) / k, terminal + (V0 - terminal) * decay


def error_at(integrator, dt, path="serial", end=1.0):
    sim = simulation(falling(), path, integrator=integrator, dt=dt)
    sim.step(round(end / dt))
    x, v = exact(end)
    return max(np.abs(sim.positions[0] - x).max(), np.abs(sim.velocities[0] - v).max())


@pytest.mark.fast_sample(integrator=["symplectic", "implicit"], path=["serial"])
@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("integrator", list(ORDER))
def test_falling_with_drag_converges_at_the_integrators_order(integrator, path):
    """Errors at t = 1 s for dt, dt/2, dt/4: each halving divides the error by 2^order
    (k dt <= 0.3 keeps every run in its asymptotic range; the errors stay far above
    round-off, so the ratios measure the method)."""
    dt = 0.05 if integrator == "rk4" else 0.02
    errors = [error_at(integrator, dt / 2 ** j, path) for j in range(3)]
    orders = [math.log2(errors[j] / errors[j + 1]) for j in range(2)]
    assert all(abs(p - ORDER[integrator]) < 0.15 for p in orders), (errors, orders)
    assert errors[-1] > 1e-9


@pytest.mark.fast_sample(integrator=["symplectic", "implicit"])
@pytest.mark.parametrize("integrator", list(ORDER))
def test_terminal_velocity(integrator):
    """After 30 time constants the velocity is m g / drag + wind: every integrator's
    fixed point of v' = g - k (v - w) is exact (the implicit one to its CG tolerance)."""
    dt = 0.01
    sim = ms.Simulation(falling(), integrator=integrator, dt=dt, **taken(integrator, {"cg_tol": 1e-13}))
    sim.step(round(30 * M / C / dt))
    np.testing.assert_allclose(sim.velocities[0], M * G / C + WIND, rtol=0, atol=1e-9)


def test_drag_is_compiled_only_when_there_is_drag():
    still = ms.Simulation(falling(drag=0.0, wind=(0.0, 0.0, 0.0)), integrator="implicit")
    assert "drag" not in still.info()["terms"]
    assert not {"drag", "wind"} & set(still.info()["arrays"])
    windy = ms.Simulation(falling(), integrator="implicit")
    assert "drag" in windy.info()["terms"] and {"drag", "wind"} <= set(windy.info()["arrays"])


@pytest.mark.parametrize("kwargs, name", [
    (dict(drag=-1.0), "drag"), (dict(drag=math.nan), "drag"), (dict(drag=[1.0, 2.0]), "drag"),
    (dict(drag="0.5"), "drag"), (dict(drag=True), "drag"),
    (dict(drag=1.0, wind=(1.0, 2.0)), "wind"), (dict(drag=1.0, wind=(math.inf, 0.0, 0.0)), "wind"),
    (dict(drag=0.0, wind=(1.0, 0.0, 0.0)), "wind"),
])
def test_bad_air_arguments_are_named(kwargs, name):
    with pytest.raises(ValueError) as info:
        ms.Model([X0], np.zeros((0, 2), dtype=int), **kwargs)
    assert str(info.value).startswith(name + ":"), info.value
