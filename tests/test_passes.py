"""The pass protocol (massspring/passes/base.py): a pass is one module and one
registration, ``Simulation`` and ``gradients`` name none; every pass's state is
snapshot and restored for a rejected step."""

import numpy as np
import pytest

import massspring as ms
from massspring.integrators import INTEGRATORS
from massspring.passes import PASSES, Pass

HEIGHT = 0.0  # m: where particle 0 starts


class HoldHeight(Pass):
    """A test-only pass: after every step, particle 0 is put back at ``HEIGHT`` with no
    vertical velocity (on the host: a pass need not have kernels)."""

    name = "hold-height"
    term = "hold-height"
    refusal = "a held height"

    @staticmethod
    def wanted(model):
        return model.n_particles > 0

    def __init__(self, dev, cfg, model, serial, dt):
        super().__init__(dev, cfg, model, serial, dt)
        self.held = 0

    def end(self, state, t):
        x, v = state.x.to_numpy(), state.v.to_numpy()
        x[0, 2], v[0, 2] = HEIGHT, 0.0
        state.x.from_numpy(x)
        state.v.from_numpy(v)
        self.held += 1

    def stats(self):
        return {"held": self.held}

    def counters(self):
        return {"held": self.held}


def chain(**changes):
    return ms.Model(**{**dict(positions=[[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.2, 0.0, 0.0]],
                              springs=[[0, 1], [1, 2]], stiffness=100.0, damping=0.1, masses=0.01), **changes})


@pytest.fixture
def hold_height(monkeypatch):
    monkeypatch.setitem(PASSES, HoldHeight.name, HoldHeight)


@pytest.mark.parametrize("integrator", ["symplectic", "implicit", "backward-euler"])
def test_a_pass_registered_from_outside_acts_after_every_step(hold_height, integrator):
    """Registered by one entry in PASSES: the run holds it, runs it after each of its
    steps, lists it among the terms, reports its stats and refuses a gradient through
    it by its name."""
    sim = ms.Simulation(chain(), integrator, dt=1e-3)
    sim.step(20)
    assert sim.positions[0, 2] == HEIGHT and sim.velocities[0, 2] == 0.0
    assert sim.positions[2, 2] < -1e-4  # the rest of the chain falls
    assert sim.pass_stats() == {"hold-height": {"held": 20}}
    assert "hold-height" in sim.info()["terms"]
    sim.close()
    with pytest.raises(ValueError, match="model: gradients through a held height are not built yet"):
        ms.gradient(chain(), lambda frames: (0.0, {}), "stiffness", steps=2, integrator=integrator)


def test_without_the_registration_no_run_holds_it():
    sim = ms.Simulation(chain(), "symplectic", dt=1e-3).step(20)
    assert sim.positions[0, 2] < 0 and sim.pass_stats() == {}
    sim.close()


def sheets_with_both_passes():
    """The stacked sheets (self-collision) at 8 x 8, shaken, with a strain limit of 0.01%."""
    model = SHEETS.model()
    shaken = np.random.default_rng(1).normal(0.0, 0.2, (model.n_particles, 3))  # m/s: stretches some springs
    return model.replaced(strain_limit=1e-4, velocities=shaken)


SHEETS = ms.load_scene("sheets").with_params(resolution=8)


@pytest.mark.fast_sample(integrator=["symplectic"])
@pytest.mark.parametrize("integrator", ["symplectic", "implicit", "bdf2"])
def test_a_restored_snapshot_continues_to_the_bit(integrator):
    """Snapshot after 15 steps, 10 more, restore, the same 10 again: the same positions,
    velocities, pass statistics and solver counters to the bit (self-collision's anchors
    and pair list, the strain limit's counters, BDF2's previous state all restored)."""
    model = sheets_with_both_passes()
    sim = ms.Simulation(model, integrator, dt=SHEETS.default_dt(integrator))
    sim.step(15)
    kept = sim.snapshot()
    sim.step(10)
    first = (sim.positions, sim.velocities, sim.pass_stats(), sim.cg_iterations, sim.newton_iterations, sim.steps)
    assert first[2]["self-collision"]["passes"] > 0 and first[2]["strain-limit"]["steps"] > 0  # both acted
    sim.restore(kept)
    assert sim.steps == 15 and len(sim.cg_iterations) == len(first[3]) - (10 if INTEGRATORS[integrator].traits.has_stats
                                                                         else 0)
    sim.step(10)
    again = (sim.positions, sim.velocities, sim.pass_stats(), sim.cg_iterations, sim.newton_iterations, sim.steps)
    np.testing.assert_array_equal(again[0], first[0])
    np.testing.assert_array_equal(again[1], first[1])
    assert again[2:] == first[2:]
    sim.close()


def test_a_snapshot_of_another_run_is_refused():
    one = ms.Simulation(chain(), "symplectic", dt=1e-3)
    other = ms.Simulation(sheets_with_both_passes(), "symplectic", dt=1e-3)
    with pytest.raises(ValueError, match="snapshot: expected a Simulation.snapshot"):
        other.restore(one.snapshot())
    one.close()
    other.close()
