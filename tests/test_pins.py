"""Kinematic pins: pinned particles moving with a prescribed constant velocity.

(The implicit step with moving pins is checked against the dense solve of Eq. 15 in
test_implicit_dense.py.)"""

import numpy as np
import pytest

import massspring as ms
from massspring.integrators import INTEGRATORS
from conftest import PATHS, simulation


def swinging(pin_velocity=((0.3, -0.2, 0.5), (-1.0, 0.0, 0.25))):
    """A 4-particle chain pinned at both ends, the pins moving apart."""
    x = [[0.0, 0.0, 0.0], [0.3, 0.0, -0.1], [0.6, 0.0, -0.1], [0.9, 0.0, 0.0]]
    return ms.Model(x, [[0, 1], [1, 2], [2, 3]], masses=0.1, stiffness=200.0, damping=0.5,
                    fixed=[3, 0], pin_velocity=[pin_velocity[1], pin_velocity[0]])


@pytest.mark.fast_sample(integrator=["symplectic", "implicit"], path=["serial"])
@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("integrator", tuple(INTEGRATORS))
def test_pins_move_exactly_with_their_velocity(integrator, path):
    """After k steps a pin is at x0 + k dt v (to the round-off of k additions) with velocity
    exactly v, while the free particles follow the springs."""
    model = swinging()
    dt, k = 2e-3, 250
    sim = simulation(model, path, integrator=integrator, dt=dt)
    sim.step(100)
    sim.step(k - 100)
    pins = model.fixed
    np.testing.assert_array_equal(sim.velocities[pins], model.pin_velocity)
    expected = model.positions[pins] + k * dt * model.pin_velocity
    np.testing.assert_allclose(sim.positions[pins], expected, rtol=0, atol=k * 4 * np.finfo(float).eps)
    moved = np.linalg.norm(sim.positions[1:3] - model.positions[1:3], axis=1)
    assert np.all(moved > 0.05)  # dragged along


def test_pin_velocity_follows_the_order_of_fixed():
    model = swinging()
    assert model.fixed.tolist() == [0, 3]
    np.testing.assert_array_equal(model.pin_velocity, [[0.3, -0.2, 0.5], [-1.0, 0.0, 0.25]])
    np.testing.assert_array_equal(model.velocities[[0, 3]], model.pin_velocity)  # initial velocity
    mask = np.array([True, False, False, True])
    same = ms.Model(model.positions, model.springs, fixed=mask, pin_velocity=[[0.3, -0.2, 0.5], [-1.0, 0.0, 0.25]])
    np.testing.assert_array_equal(same.pin_velocity, model.pin_velocity)
    twice = ms.Model(model.positions, model.springs, fixed=[3, 0, 3], pin_velocity=[[1, 0, 0], [0, 0, 0], [1, 0, 0]])
    np.testing.assert_array_equal(twice.pin_velocity, [[0, 0, 0], [1, 0, 0]])


@pytest.mark.parametrize("kwargs", [
    dict(fixed=[0, 3], pin_velocity=[[1.0, 0.0, 0.0]]),
    dict(fixed=[0, 3], pin_velocity=[[1.0, 0.0], [0.0, 0.0]]),
    dict(fixed=None, pin_velocity=[[1.0, 0.0, 0.0]]),
    dict(fixed=[0, 3], pin_velocity=[[np.nan, 0.0, 0.0], [0.0, 0.0, 0.0]]),
    dict(fixed=[0, 0], pin_velocity=[[1.0, 0.0, 0.0], [2.0, 0.0, 0.0]]),
    dict(fixed=[0, 3], pin_velocity=[["a", 0, 0], [0, 0, 0]]),
])
def test_bad_pin_velocity_is_named(kwargs):
    model = swinging()
    with pytest.raises(ValueError) as info:
        ms.Model(model.positions, model.springs, **kwargs)
    assert str(info.value).startswith("pin_velocity:"), info.value


def test_pin_velocity_read_only_when_a_pin_moves():
    still = swinging(((0.0, 0.0, 0.0), (0.0, 0.0, 0.0)))
    assert not still.has_moving_pins
    info = ms.Simulation(still, integrator="implicit").info()
    assert "pin_velocity" not in info["arrays"] and "moving-pins" not in info["terms"]
    info = ms.Simulation(swinging(), integrator="implicit").info()
    assert "pin_velocity" in info["arrays"] and "moving-pins" in info["terms"]
