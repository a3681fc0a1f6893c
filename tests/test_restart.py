"""Restart: a run continued from a saved state equals the unbroken run to the bit (f64, every
integrator); states of another model, count or dt, and broken state files, are refused."""

import numpy as np
import pytest

import massspring as ms
from conftest import PATHS, random_system


@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("integrator", ["explicit", "symplectic", "implicit", "rk4"])
def test_set_state_continues_bitwise(integrator, path):
    model = random_system(3)
    whole = ms.Simulation(model, integrator=integrator, dt=2e-3, loops=path).step(12)
    part = ms.Simulation(model, integrator=integrator, dt=2e-3, loops=path).step(5)
    x, v = part.positions, part.velocities
    part.close()
    rest = ms.Simulation(model, integrator=integrator, dt=2e-3, loops=path).set_state(x, v, steps=5).step(7)
    assert rest.steps == 12 and rest.time == whole.time
    assert np.array_equal(rest.positions, whole.positions) and np.array_equal(rest.velocities, whole.velocities)
    whole.close()
    rest.close()


def test_set_state_checks_its_arguments():
    model = random_system(4, n=8, n_fixed=1)
    sim = ms.Simulation(model, integrator="symplectic", dt=1e-3)
    pinned = int(model.fixed[0])
    x, v = model.positions.copy(), np.zeros((8, 3))
    for kwargs, word in ((dict(positions=x[:7], velocities=v), "positions: expected shape (8, 3)"),
                         (dict(positions=x, velocities=v.ravel()), "velocities: expected shape"),
                         (dict(positions=np.where(x == x[0, 0], np.nan, x), velocities=v), "positions: contains"),
                         (dict(positions=x, velocities=v, steps=-1), "steps"),
                         (dict(positions=x, velocities=np.where(np.arange(8)[:, None] == pinned, 1.0, v)),
                          f"velocities: particle {pinned} is fixed")):
        with pytest.raises(ValueError, match=word.replace("(", r"\(").replace(")", r"\)")):
            sim.set_state(**kwargs)
    assert sim.steps == 0 and np.array_equal(sim.positions, model.positions)  # nothing was changed
    sim.close()
