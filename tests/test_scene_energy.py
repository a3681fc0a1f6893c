"""Every shipped scene's default run never gains energy it was not given.

The total energy (kinetic + spring + gravity, ``Model.energy``) of a scene run at its
default integrator and dt, for its whole default duration, never rises above its start
plus the work done on it from outside: by moving pins (the constraint force on a
pin, minus the other forces on it, times its velocity) and by the wind (the drag
force's part c wind . v; its other part -c |v|^2 only dissipates). Both works are
integrated with the trapezoidal rule over the steps, and the bound allows that
rule's error (a tenth of the work so far) plus round-off.
"""

import numpy as np
import pytest

from massspring.integrators import INTEGRATORS
from massspring.scene import builtin_scenes, load_scene
from conftest import FULL, numpy_forces, sampled

CONTACT_GAIN = pytest.mark.xfail(strict=True, reason=(
    "known limitation of the contact model (kernels/contact.py), whatever the integrator: a particle that "
    "meets a collider within a large step is moved onto its surface along the normal, stretching its springs "
    "at the impact: drape +7.6 J (implicit) / +6.2 J (backward-euler) at dt 1/60 with its strain limit (+8.4 J / "
    "+8.7 J without), none at dt 0.004; "
    "rope-drop +3.7 J / +1.8 J at dt 0.005; ledge (16 x 16, with or without self-collision) +0.94 J at dt 1/240, "
    "+0.045 J at 1/480, none at 1/960, as the hanging part hits the ground"))
SIZES = {"cloth": {"resolution": 24}, "drape": {"resolution": 16}, "tablecloth": {"resolution": 16},
         "flag": {"resolution": 16}, "swing": {"resolution": 16}, "ledge": {"resolution": 16}}  # smaller grids: the same physics, faster


def external_power(model, x, v):
    """Power (W) put in by moving pins and the wind at the state (x, v)."""
    power = model.drag * float(np.sum(v @ model.wind))
    if model.has_moving_pins:
        pins = model.fixed
        power -= float(np.sum(numpy_forces(model, x, v)[pins] * model.pin_velocity))
    return power


GAINS = ("drape", "rope-drop", "ledge")  # CONTACT_GAIN's scenes


@pytest.mark.parametrize("name", sampled([pytest.param(n, marks=CONTACT_GAIN) if n in GAINS
                                          else n for n in sorted(builtin_scenes())], {"spring", "chain"}))
def test_default_run_never_gains_energy(name):
    scene = load_scene(name).with_params(**SIZES.get(name, {}))
    sim = scene.simulation()
    model = sim.model
    e0 = sim.energy()["total"]
    work, power = 0.0, external_power(model, model.positions, model.velocities)
    scale = abs(e0) + float(np.sum(model.masses)) * 9.81
    for _ in range(int(round(scene.duration / sim.dt))):
        sim.step()
        x, v = sim.positions, sim.velocities
        after = external_power(model, x, v)
        work += 0.5 * sim.dt * (power + after)
        power = after
        gain = sim.energy()["total"] - e0
        assert gain <= max(work, 0.0) * 1.1 + 1e-9 * scale, (sim.time, gain, work)


SMALL_SCENES = sorted(name for name in builtin_scenes() if load_scene(name).counts()[0] <= 216)
MOST_STEPS = 1_000_000  # longer runs (80 million explicit steps of the heavy chain) are left to test_cli's first 100
# test_default_run_never_gains_energy runs these whole at their default dt (a divergence fails it)
ENERGY_RUNS = [(name, load_scene(name).integrator) for name in SMALL_SCENES if name not in GAINS + tuple(SIZES)]
WHOLE_RUNS = [(name, integrator) for name in SMALL_SCENES for integrator in sorted(INTEGRATORS)
              if (name, integrator) != ("stiffchain", "explicit")  # undamped: grows at every dt, the scene's point
              and (name, integrator) not in ENERGY_RUNS
              and load_scene(name).duration / load_scene(name).default_dt(integrator) <= MOST_STEPS]


@FULL
@pytest.mark.parametrize("name, integrator", WHOLE_RUNS)
def test_every_small_scene_runs_its_whole_duration_at_its_default_dt(name, integrator):
    """Every shipped scene of at most 216 particles, with every integrator at the scene's
    default dt for it, runs its whole default duration without a divergence (the CLI's
    exit 3). Left out: explicit Euler on the undamped stiff chain, which grows at every dt
    (the scene's point: ``test_cli`` checks its exit 3), and the four runs of more than a
    million steps (the heavy chain's explicit, symplectic and RK4 runs, the stiff cloth's
    explicit one: 17-50 s each, run whole once for issue 60 and passing), and the runs
    with the scene's own integrator that ``test_default_run_never_gains_energy`` runs
    whole (``ENERGY_RUNS``). The larger
    scenes' midpoint runs are ``benchmarks/midpoint_dt.py``'s (docs/stability-and-study.md)."""
    scene = load_scene(name)
    sim = scene.simulation(integrator=integrator)
    try:
        sim.step(int(round(scene.duration / sim.dt)))
    finally:
        sim.close()
