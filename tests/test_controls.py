"""Time-varying controls (``massspring.Controls``, issue 39): keyframed pins reach their
targets, wind and rest lengths per interval step as a chain of runs of fixed values
does, their gradients agree with central differences, and bad controls are refused
before any step."""

import numpy as np
import pytest

import massspring as ms
from massspring.model import ordering
from massspring.integrators import INTEGRATORS
from test_gradient import PINNED, SOLVED, directional_difference, objective, sheet

DT = 2e-3
PER = 3  # steps an interval
INTERVALS = 3
SPRINGS = np.array([0, 5, 7])  # the actuated springs
KEYFRAMED = tuple(name for name, cls in INTEGRATORS.items() if cls.traits.keyframed_pins)


def control_values(seed=5):
    """Pin targets wandering from the pins' start, a wind and the actuated springs' rest
    lengths changing every interval."""
    rng = np.random.default_rng(seed)
    start = sheet(pin_velocity=None).positions[PINNED]
    return dict(pin_targets=start[None] + np.cumsum(rng.normal(0, 0.003, (INTERVALS, len(PINNED), 3)), axis=0),
                wind=rng.normal(0, 2.0, (INTERVALS, 3)),
                rest_lengths=sheet().rest_lengths[SPRINGS][None] * rng.uniform(0.8, 1.2, (INTERVALS, SPRINGS.size)))


def controlled(pin_targets=None, wind=None, rest_lengths=None, **changes):
    controls = ms.Controls(PER * DT, pin_targets=pin_targets, wind=wind,
                           springs=None if rest_lengths is None else SPRINGS, rest_lengths=rest_lengths)
    return sheet(pin_velocity=None, controls=controls, **changes)


@pytest.mark.fast_sample(integrator=["midpoint"])
@pytest.mark.parametrize("integrator", KEYFRAMED)
def test_keyframed_pins_reach_their_targets_and_stop_after_the_last(integrator):
    """A pin moves in a straight line to each target over its interval (its position at
    the interval's end is the target to round-off, its velocity (P_s - P_s-1) / T), then
    stands at the last target with velocity 0."""
    targets = control_values()["pin_targets"]
    model = controlled(pin_targets=targets)
    start = model.positions[PINNED]
    assert np.allclose(model.pin_velocity, (targets[0] - start) / (PER * DT), rtol=1e-14)
    sim = ms.Simulation(model, integrator, dt=DT, **SOLVED.get(integrator, {}))
    for s in range(INTERVALS + 2):
        sim.step(PER)
        last = min(s, INTERVALS - 1)
        assert np.abs(sim.positions[PINNED] - targets[last]).max() <= 1e-15
        before = targets[s - 1] if 0 < s < INTERVALS else start
        velocity = (targets[s] - before) / (PER * DT) if s < INTERVALS else np.zeros((len(PINNED), 3))
        assert np.allclose(sim.velocities[PINNED], velocity, rtol=1e-12, atol=1e-14)
    assert sim.info()["terms"][-1] == "controls (pin_targets)"
    sim.close()


@pytest.mark.fast_sample(integrator=["implicit"])
@pytest.mark.parametrize("integrator", tuple(INTEGRATORS))
def test_wind_and_rest_lengths_step_as_a_chain_of_runs_with_fixed_values(integrator):
    """Interval by interval, a run with controls equals a chain of runs of models that
    hold each interval's wind and rest lengths throughout, each continued from the last
    one's state (with its carried state): the controls change nothing else."""
    values = control_values()
    wind, rest = values["wind"], values["rest_lengths"]
    options = dict(dt=DT)  # the solvers' defaults: both runs solve the same equations
    sim = ms.Simulation(controlled(wind=wind, rest_lengths=rest), integrator, **options)
    state = None
    for s in range(INTERVALS + 1):
        held = min(s, INTERVALS - 1)
        lengths = sheet().rest_lengths.copy()
        lengths[SPRINGS] = rest[held]
        chain = ms.Simulation(sheet(pin_velocity=None, wind=wind[held], rest_lengths=lengths), integrator,
                              **options)
        if state is not None:
            chain.set_state(*state, steps=s * PER, carried=carried)
        chain.step(PER)
        sim.step(PER)
        assert np.allclose(sim.positions, chain.positions, rtol=0, atol=1e-13)
        assert np.allclose(sim.velocities, chain.velocities, rtol=0, atol=1e-11)
        state, carried = (chain.positions, chain.velocities), chain.carried_state()
        chain.close()
    sim.close()


def test_the_divergence_bound_counts_what_the_controls_drive():
    """Actuated rest lengths do work on the particles (a muscle moving its ends as a pin
    would): the divergence check's floor counts the fastest change of one, |dl0| / T, as
    it counts the fastest pin and wind (a crawling creature was called runaway before)."""
    from massspring.engine.simulation import divergence_check

    values = control_values()
    plain = sheet(pin_velocity=None, wind=np.zeros(3))
    lengths = np.concatenate([plain.rest_lengths[SPRINGS][None], values["rest_lengths"]])
    rate = np.abs(np.diff(lengths, axis=0)).max() / (PER * DT)
    model = sheet(pin_velocity=None, wind=np.zeros(3), controls=ms.Controls(
        PER * DT, springs=SPRINGS, rest_lengths=values["rest_lengths"]))
    size = float(np.linalg.norm(np.ptp(plain.positions, axis=0)))
    energy = plain.energy(plain.positions, plain.velocities)
    floor = divergence_check(model)[0] - energy["kinetic"] - energy["spring"]
    assert rate > 1 and floor == pytest.approx(0.5 * plain.masses.sum() * (size + rate) ** 2, rel=1e-12)
    assert divergence_check(plain)[0] < divergence_check(model)[0]


CONTROL_NAMES = ("controls.pin_targets", "controls.wind", "controls.rest_lengths")


@pytest.mark.fast_sample(integrator=["symplectic"])
@pytest.mark.parametrize("integrator", ms.gradients.differentiable())
def test_control_gradients_match_central_differences(integrator):
    """Each control's gradient along a random direction against central differences of
    the forward runs (as ``test_gradient``'s parameters), to 1e-6 relative; 10 steps over
    three intervals of 3 and one after the last; RK4 without keyframed pins."""
    values = control_values()
    if integrator not in KEYFRAMED:
        del values["pin_targets"]
    run = dict(steps=10, every=2, dt=DT, checkpoint=4, integrator=integrator, **SOLVED.get(integrator, {}))
    names = ["controls." + key for key in values] + ["rest_lengths"]
    value, grads = ms.gradient(controlled(**values), objective, names, **run)
    assert np.all(grads["rest_lengths"][SPRINGS] == 0)  # the controls set them
    rng = np.random.default_rng(11)
    for key in values:
        gradient = grads["controls." + key]
        assert gradient.shape == values[key].shape
        direction = rng.normal(size=values[key].shape)
        direction /= np.abs(direction).max()
        numeric = directional_difference(controlled, values, key, direction, integrator, run)
        exact = float(np.sum(gradient * direction))
        assert abs(exact - numeric) <= 1e-6 * abs(numeric), (key, exact, numeric)


def test_controls_of_a_renumbered_model_follow_its_pins_and_springs(monkeypatch):
    """A scrambled sheet that the run renumbers has the gradients of the sheet itself,
    permuted: the controls' pin rows and actuated springs follow the renumbering."""
    monkeypatch.setattr(ordering, "WINDOW", 4)
    values = control_values()
    model = controlled(**values)
    rng = np.random.default_rng(2)
    particles, springs = rng.permutation(model.n_particles), rng.permutation(model.n_springs)
    inverse = np.argsort(particles)
    pins = inverse[PINNED]
    controls = ms.Controls(PER * DT, pin_targets=values["pin_targets"][:, np.argsort(pins)], wind=values["wind"],
                           springs=np.argsort(springs)[SPRINGS], rest_lengths=values["rest_lengths"])
    scrambled = ms.Model(model.positions[particles], inverse[model.springs][springs], masses=model.masses[particles],
                         stiffness=model.stiffness[springs], damping=model.damping[springs],
                         rest_lengths=model.rest_lengths[springs], velocities=model.velocities[particles],
                         gravity=model.gravity, fixed=pins, controls=controls, drag=model.drag, wind=model.wind)
    assert ordering.plan(scrambled) is not None

    def moved(frames):
        c = np.random.default_rng(7).normal(size=frames.positions.shape)
        return float(np.sum(c * frames.positions)), {"positions": c}

    def scrambled_objective(frames):
        value, partials = moved(type(frames)(frames.positions[:, inverse], frames.velocities[:, inverse],
                                             frames.times, frames.steps))
        return value, {"positions": partials["positions"][:, particles]}

    run = dict(steps=8, every=2, dt=DT, integrator="symplectic")
    names = list(CONTROL_NAMES)
    _, want = ms.gradient(model, moved, names, **run)
    _, got = ms.gradient(scrambled, scrambled_objective, names, **run)
    for name in names:
        assert np.allclose(got[name], want[name], rtol=1e-10, atol=1e-12 * np.abs(want[name]).max()), name


def test_bad_controls_are_refused_naming_what_is_wrong():
    values = control_values()
    with pytest.raises(ValueError, match="controls.interval"):
        ms.Controls(0.0, wind=values["wind"])
    with pytest.raises(ValueError, match="at least one"):
        ms.Controls(0.1)
    with pytest.raises(ValueError, match=r"controls.wind: expected shape \(S, 3\)"):
        ms.Controls(0.1, wind=np.zeros((2, 2)))
    with pytest.raises(ValueError, match="same number of intervals"):
        ms.Controls(0.1, wind=np.zeros((2, 3)), springs=[0], rest_lengths=np.ones((3, 1)))
    with pytest.raises(ValueError, match="springs and rest_lengths go together"):
        ms.Controls(0.1, rest_lengths=np.ones((3, 1)))
    with pytest.raises(ValueError, match="controls.springs: a spring is listed twice"):
        ms.Controls(0.1, springs=[1, 1], rest_lengths=np.ones((3, 2)))
    with pytest.raises(ValueError, match="controls.springs: expected spring indices"):  # ragged (issue 60's re-run)
        ms.Controls(0.1, springs=[[0], [1, 2]], rest_lengths=np.ones((2, 2)))
    with pytest.raises(ValueError, match="controls.rest_lengths: rest lengths must be >= 0"):
        ms.Controls(0.1, springs=[1], rest_lengths=-np.ones((3, 1)))
    with pytest.raises(ValueError, match=r"controls.pin_targets: expected shape \(S, 2, 3\)"):
        controlled(pin_targets=np.zeros((3, 3, 3)))
    with pytest.raises(ValueError, match="controls.springs: spring 99 is outside"):
        sheet(controls=ms.Controls(0.1, springs=[99], rest_lengths=np.ones((3, 1))))
    with pytest.raises(ValueError, match="controls.wind: the model has no air drag"):
        sheet(pin_velocity=None, drag=0.0, wind=np.zeros(3), controls=ms.Controls(0.1, wind=values["wind"]))
    with pytest.raises(ValueError, match="pin_velocity: the pins follow controls.pin_targets"):
        sheet(controls=ms.Controls(0.1, pin_targets=values["pin_targets"]))
    with pytest.raises(ValueError, match="controls: expected a massspring.Controls"):
        sheet(controls={"wind": values["wind"]})
    model = controlled(**values)
    with pytest.raises(ValueError, match="dt: controls.interval 0.006 s is not a whole number of steps of 0.004 s"):
        ms.Simulation(model, "symplectic", dt=0.004)
    with pytest.raises(ValueError, match="integrator: 'rk4' does not move keyframed pins"):
        ms.Simulation(model, "rk4", dt=DT)
    with pytest.raises(ValueError, match="wrt: 'wind': the model's controls.wind set it over time"):
        ms.gradient(model, objective, "wind", steps=2, dt=DT)
    with pytest.raises(ValueError, match="wrt: 'pin_velocity': the model's controls.pin_targets"):
        ms.gradient(model, objective, "pin_velocity", steps=2, dt=DT)
    with pytest.raises(ValueError, match="wrt: 'controls.wind': the model has no controls.wind"):
        ms.gradient(sheet(), objective, "controls.wind", steps=2, dt=DT)
