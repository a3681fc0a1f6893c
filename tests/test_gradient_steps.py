"""Gradients through steps of varying size (issue 62): ``massspring.gradient(dts=...)``
differentiates a run whose step sizes are given and frozen (``Simulation.replay``),
``gradient(tol=, times=)`` one whose steps an error-controlled run chose. Checked against
central differences of forward runs with the same steps (``replayed_value``)."""

import numpy as np
import pytest

import massspring as ms
from conftest import FULL
from massspring.gradients import Frames
from test_controls import INTERVALS, PER, DT, control_values, controlled
from test_gradient import (DIFFERENTIABLE, PARAMETERS, REPULSION_STEP, SOLVED, STILL_AIR, model_values, objective, sheet,
                           straddling, unit_direction)

SIZES = np.random.default_rng(0).uniform(1e-3, 3e-3, 10)  # ratios between neighbours 0.4 to 2.7
AT = [2, 4, 7, 10]  # the frames' steps (and step 0)
EPS = 1e-4  # central differences' step relative to the largest value, Richardson-combined: O(EPS^4)


def replayed_value(model, integrator, sizes, at, **options):
    """The objective of a forward run of ``model`` with steps of ``sizes``, frames at step 0 and ``at``."""
    sim = ms.Simulation(model, integrator, dt=float(sizes[0]) if model.controls is None else model.controls.interval,
                        **options)
    sim.replay(sizes[:0])
    positions, velocities, done = [sim.positions], [sim.velocities], 0
    for k in at:
        sim.replay(sizes[done:k])
        done = k
        positions.append(sim.positions)
        velocities.append(sim.velocities)
    sim.close()
    return objective(Frames(np.array(positions), np.array(velocities), None, np.array([0, *at])))[0]


def directional(make, values, name, direction, integrator, sizes, at, options, step=EPS):
    eps = step * max(1.0, np.abs(values[name]).max())

    def central(e):
        ends = [replayed_value(make(**dict(values, **{name: values[name] + sign * e * direction})), integrator, sizes,
                               at, **options) for sign in (1, -1)]
        return (ends[0] - ends[1]) / (2 * e)

    return (4 * central(eps) - central(2 * eps)) / 3


@pytest.mark.fast_sample(integrator=["implicit"])
@pytest.mark.parametrize("integrator", DIFFERENTIABLE)
def test_steps_of_one_size_give_the_fixed_dt_gradient(integrator):
    """``dts`` of ten equal sizes: the value of ten steps of that dt to the bit, and its
    gradient to 1e-12 of each parameter's largest entry (measured: equal, BDF2 8e-16: its
    variable-step coefficients (4 x_n - x_{n-1}) / 3 summed otherwise)."""
    model = sheet()
    options = SOLVED.get(integrator, {})
    value, grads = ms.gradient(model, objective, PARAMETERS, steps=10, every=2, dt=2e-3, integrator=integrator,
                               **options)
    again, frozen = ms.gradient(model, objective, PARAMETERS, dts=np.full(10, 2e-3), every=2, integrator=integrator,
                                **options)
    assert again == value
    for name in PARAMETERS:
        scale = np.abs(grads[name]).max()
        assert np.abs(frozen[name] - grads[name]).max() <= 1e-12 * scale, name


@pytest.mark.fast_sample(integrator=["bdf2"])
@pytest.mark.parametrize("integrator", DIFFERENTIABLE)
def test_gradients_through_frozen_steps_match_central_differences(integrator):
    """Ten steps of sizes 1 to 3 ms in no order, frames at steps 2, 4, 7 and 10, kept
    states every 3 steps (stretches run again): every parameter kind's directional
    derivative agrees with central differences of runs with the same steps to 1e-6
    relative; BDF2's through its variable-step coefficients."""
    model = sheet()
    options = SOLVED.get(integrator, {})
    value, grads = ms.gradient(model, objective, PARAMETERS, dts=SIZES, every=AT, checkpoint=3,
                               integrator=integrator, **options)
    assert value == replayed_value(model, integrator, SIZES, AT, **options)
    values = model_values(model)
    rng = np.random.default_rng(3)
    for name in PARAMETERS:
        direction = unit_direction(rng, values, name)
        numeric = directional(sheet, values, name, direction, integrator, SIZES, AT, options)
        exact = float(np.sum(grads[name] * direction))
        assert abs(exact - numeric) <= 1e-6 * abs(numeric), (name, exact, numeric)


@pytest.mark.fast_sample(integrator=["implicit"])
@pytest.mark.parametrize("integrator", ["implicit", "bdf2"])
def test_an_error_controlled_gradient_is_that_of_its_chosen_steps(integrator):
    """Keyframed pins, wind and rest lengths over intervals that the chosen steps do not
    divide: ``gradient(tol=, times=)`` lands a frame on each time, equals the gradient of
    ``dts`` = the error-controlled run's ``step_sizes`` to the bit, and its derivatives in
    the controls agree with central differences of runs with those steps to 1e-6."""
    values = control_values()
    model = controlled(**values)
    options = SOLVED.get(integrator, {})
    times = np.array([0.5, 1.0, 1.5]) * INTERVALS * PER * DT
    names = ["controls.pin_targets", "controls.wind", "controls.rest_lengths", "stiffness"]
    seen = []

    def watched(frames):
        seen.append(frames)
        return objective(frames)

    value, grads = ms.gradient(model, watched, names, tol=1e-4, times=times, integrator=integrator, dt=DT, **options)
    sim = ms.Simulation(model, integrator, dt=DT, tol=1e-4, horizon=times[-1])
    at = []
    ms.run(sim, duration=times[-1], frames=times.tolist(), on_frame=lambda s: at.append(s.steps))
    sizes = sim.step_sizes
    assert len(sizes) == sim.steps > 3 * INTERVALS and np.ptp(sizes) > 0  # steps of varying size, not whole intervals
    np.testing.assert_allclose(seen[0].times, [0.0, *times], rtol=1e-12)
    assert seen[0].steps.tolist() == [0, *at]
    again, frozen = ms.gradient(model, objective, names, dts=sizes, every=at, integrator=integrator, **options)
    assert again == value and all(np.array_equal(frozen[name], grads[name]) for name in names)
    make = lambda **v: controlled(**{k: v[k] for k in values}, stiffness=v["stiffness"])  # noqa: E731
    everything = {**values, "stiffness": model.stiffness}
    rng = np.random.default_rng(4)
    for name in names:
        key = name.split(".")[-1]
        direction = rng.normal(size=np.shape(everything[key]))
        direction /= np.abs(direction).max()
        numeric = directional(make, everything, key, direction, integrator, sizes, at, options)
        exact = float(np.sum(grads[name] * direction))
        assert abs(exact - numeric) <= 1e-6 * abs(numeric), (name, exact, numeric)


def test_bad_step_arguments_are_refused_by_name():
    model = sheet()
    cases = [
        (dict(steps=3, dts=[1e-3, 1e-3]), "steps: 3 is not len"),
        (dict(dts=[1e-3, -1e-3]), "dts: expected"),
        (dict(dts=[[1e-3]]), "dts: expected"),
        (dict(dts=[1e-3] * 4, every=[3, 2]), "every: expected"),
        (dict(dts=[1e-3] * 4, every=[5]), "every: expected"),
        (dict(steps=4, every=[[1], [2, 3]]), "every: expected"),  # ragged (the fuzz re-run of issue 60)
        (dict(tol=1e-3), "times: an error-controlled gradient needs"),
        (dict(times=[0.1]), "tol: an error-controlled gradient needs"),
        (dict(tol=1e-3, times=[0.1], steps=4), "steps: with tol"),
        (dict(tol=1e-3, times=[0.1], every=2), "every: with tol"),
        (dict(tol=1e-3, times=[0.2, 0.1]), "times: expected increasing"),
        (dict(steps=4, min_dt=1e-3), "min_dt: only with tol"),
        (dict(), "steps: give the number of steps"),
    ]
    for kwargs, message in cases:
        with pytest.raises(ValueError, match=message):
            ms.gradient(model, objective, "stiffness", **kwargs)


def test_replay_is_for_a_fixed_dt_run_from_its_start():
    model = sheet()
    sim = ms.Simulation(model, "symplectic", dt=1e-3)
    sim.step(1)
    with pytest.raises(ValueError, match="sizes: a run of fixed steps replays from its start only"):
        sim.replay([1e-3])
    with pytest.raises(ValueError, match="sizes: an error-controlled run"):
        ms.Simulation(model, "symplectic", dt=1e-3, tol=1e-3).replay([1e-3])
    with pytest.raises(ValueError, match="sizes: expected"):
        ms.Simulation(model, "symplectic", dt=1e-3).replay([1e-3, 0.0])
    sim = ms.Simulation(model, "symplectic", dt=1e-3).replay(SIZES[:4])
    assert sim.steps == 4 and sim.time == SIZES[0] + SIZES[1] + SIZES[2] + SIZES[3]
    assert np.array_equal(sim.step_sizes, SIZES[:4])


@FULL
@pytest.mark.parametrize("integrator", ["symplectic", "implicit", "backward-euler"])
def test_gradients_through_self_collision_with_steps_of_varying_size(integrator):
    """test_gradient's straddling triangle, repelled every step (sliding friction), over ten
    steps of 1 to 3 ms: each step's pass is replayed and run backwards with its own size
    (and the linearised step's solve pairs' share with it); every parameter kind against
    central differences of runs with the same steps, 1e-6 relative (the difference steps
    of test_gradient's repulsion test, but the positions': with these steps 2e-5 m crosses
    a switch of the implicit run's pairs, measured: -5853 against the gradient's -123.67,
    which differences of 1e-6 and 1e-7 m give). Before, the linearised step's solve
    penalties kept the previous step's size (h^2 k, collected at its end): the masses'
    derivative was 42% off."""
    model = straddling(0.05)
    options = SOLVED.get(integrator, {})
    value, grads = ms.gradient(model, objective, STILL_AIR, dts=SIZES, every=AT, checkpoint=3,
                               integrator=integrator, **options)
    assert value == replayed_value(model, integrator, SIZES, AT, **options)
    values = model_values(model)
    rng = np.random.default_rng(3)
    for name in STILL_AIR:
        direction = rng.normal(size=np.shape(values[name]))
        direction /= np.abs(direction).max()
        numeric = directional(lambda **changes: straddling(0.05, **changes), values, name, direction, integrator,
                              SIZES, AT, options, dict(REPULSION_STEP, positions=1e-6).get(name, 1e-4))
        exact = float(np.sum(grads[name] * direction))
        assert abs(exact - numeric) <= 1e-6 * abs(numeric), (name, exact, numeric)


def test_a_gradients_memory_check_counts_the_self_collision_records(monkeypatch):
    """``gradients.host_bytes`` (the memory check before a gradient runs) adds, for each step
    of a stretch, the self-collision pass's ``Record`` (48 bytes a particle, 56 a listed pair
    at the pair list's first capacity of 8 a particle) and with the linearised step its
    solve's pairs (104 bytes a pair at the solve's capacity of 16 a particle, 4 a particle);
    the records a run keeps stay within that, step by step."""
    from massspring.gradients import host_bytes
    from massspring.passes.self_collision.backward import PassSteps

    model = straddling(0.05)
    free = model.replaced(self_collision=None)
    n = model.n_particles
    for integrator, solve in (("symplectic", 0), ("implicit", 4 + 104 * 16)):
        counted = host_bytes(model, integrator, 100, 5, 40) - host_bytes(free, integrator, 100, 5, 40)
        assert counted == 40 * n * (48 + 56 * 8 + solve), integrator
    kept = []
    record = PassSteps.__call__

    def spy(self, *args):
        record(self, *args)
        step = self.records[self.sim.steps]
        kept.append(sum(value.nbytes for value in vars(step).values()))
    monkeypatch.setattr(PassSteps, "__call__", spy)
    ms.gradient(model, objective, "stiffness", steps=10, integrator="symplectic", dt=2e-3)
    assert len(kept) == 10 and max(kept) <= n * (48 + 56 * 8)
