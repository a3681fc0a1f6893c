"""Feedback controls (``massspring.Controller``, ``massspring.SineNetwork``, issue 63): a
controller chooses each interval's controls from the state the run enters it in, the run
equals an open-loop run of the values it chose, and ``massspring.gradient`` goes through
its vector-Jacobian product into its parameters and the states it read, checked against
central differences of forward runs; bad controllers are refused by name."""

import numpy as np
import pytest

import massspring as ms
from conftest import FULL
from massspring.model.feedback import ControlState
from test_controls import KEYFRAMED
from test_gradient import PINNED, SOLVED, STEP, objective, sheet
from test_gradient import run_value as forward_value

DT = 2e-3
PER = 3  # steps an interval
INTERVALS = 3
SPRINGS = np.array([0, 5, 7])  # the actuated springs
RUN = dict(steps=10, every=2, dt=DT, checkpoint=4)  # three intervals and a step after the last
NAMES = ("controller.w1", "controller.b1", "controller.w2", "controller.b2", "positions", "velocities", "stiffness")


def network(**changes):
    """A network watching six free particles of the sheet, its biases off zero: every
    parameter and the state it reads move the rest lengths."""
    free = np.array([i for i in range(sheet().n_particles) if i not in PINNED])
    options = dict(hidden=5, waves=3, omega=40.0, position_scale=5.0, velocity_scale=1.0, seed=3)
    options.update(changes)
    net = ms.SineNetwork(PER * DT, SPRINGS, sheet().rest_lengths[SPRINGS], 0.2, free[:6], **options)
    net.parameters["b1"][:] = 0.3
    net.parameters["b2"][:] = -0.2
    return net


def controlled(**changes):
    return sheet(pin_velocity=None, controls=network().controls_for(INTERVALS), **changes)


def run_value(model, controller, integrator, options):
    """The objective of a plain forward run (``test_gradient.run_value``) with ``controller``."""
    return forward_value(model, objective, dict(RUN, integrator=integrator, controller=controller, **options))


def perturbed(name, e, direction):
    """(model, controller) with ``name`` moved by e * direction."""
    net = network()
    if name.startswith("controller."):
        key = name.split(".", 1)[1]
        net.parameters[key] = net.parameters[key] + e * direction
        return controlled(), net
    return controlled(**{name: getattr(controlled(), name) + e * direction}), net


def scale(name):
    if name.startswith("controller."):
        return np.abs(network().parameters[name.split(".", 1)[1]]).max()
    return np.abs(getattr(controlled(), name)).max()


@pytest.mark.fast_sample(integrator=["symplectic"])
@pytest.mark.parametrize("integrator", ms.gradients.differentiable())
def test_gradients_through_a_feedback_controller_match_central_differences(integrator):
    """The network's parameters, the initial state (which the network reads at every
    interval's start) and a model parameter: directional derivatives within 1e-6 of
    central differences (Richardson-combined for the Newton-solved steps, as
    ``test_gradient``). Without the controller's share of the state's adjoint, the
    symplectic run's derivatives are off by 1e-3 to 2.5e-2 relative (measured)."""
    options = SOLVED.get(integrator, {})
    value, grads = ms.gradient(controlled(), objective, list(NAMES), integrator=integrator, controller=network(),
                               **RUN, **options)
    assert value == pytest.approx(run_value(controlled(), network(), integrator, options), rel=1e-12)
    rng = np.random.default_rng(0)
    for name in NAMES:
        gradient = grads[name]
        direction = rng.normal(size=gradient.shape)
        if name in ("positions", "velocities"):
            direction[PINNED] = 0
        direction /= np.abs(direction).max()
        eps = STEP.get(integrator, 1e-6) * max(1.0, scale(name))

        def central(e):
            ends = [run_value(*perturbed(name, sign * e, direction), integrator, options) for sign in (1, -1)]
            return (ends[0] - ends[1]) / (2 * e)

        numeric = central(eps) if integrator not in STEP else (4 * central(eps) - central(2 * eps)) / 3
        exact = float(np.sum(gradient * direction))
        assert abs(exact - numeric) <= 1e-6 * abs(numeric), (name, exact, numeric)


@pytest.mark.fast_sample(integrator=["implicit"])
@pytest.mark.parametrize("integrator", ["symplectic", "implicit", "backward-euler"])
def test_a_feedback_run_is_the_open_loop_run_of_the_values_it_chose(integrator):
    """The controller is called once an interval, with the state at the interval's start,
    and the run equals to the bit an open-loop run of the rest lengths it chose."""
    calls = []

    class Recording(ms.SineNetwork):
        def controls(self, state):
            calls.append(state)
            return super().controls(state)

    net = network()
    recording = Recording(PER * DT, SPRINGS, net.rest, 0.2, net.particles, hidden=5, waves=3, omega=40.0,
                          position_scale=5.0, velocity_scale=1.0, seed=3)
    recording.parameters = net.parameters
    sim = ms.Simulation(controlled(), integrator, dt=DT, controller=recording)
    starts = []
    for _ in range(INTERVALS + 1):
        starts.append((sim.positions, sim.velocities))
        sim.step(PER)
    assert [c.interval for c in calls] == list(range(INTERVALS))
    for call, (x, v) in zip(calls, starts):
        assert call.time == call.interval * PER * DT
        assert np.array_equal(call.positions, x) and np.array_equal(call.velocities, v)
    chosen = sim.schedule.values["rest_lengths"]
    assert np.all(chosen != net.rest) and np.all(np.abs(chosen / net.rest - 1) < 0.2)
    plain = ms.Simulation(sheet(pin_velocity=None, controls=ms.Controls(PER * DT, springs=SPRINGS,
                                                                        rest_lengths=chosen)), integrator, dt=DT)
    plain.step(sim.steps)
    assert np.array_equal(plain.positions, sim.positions) and np.array_equal(plain.velocities, sim.velocities)
    # set back to the start: the controller chooses again, from the state given
    sim.set_state(*starts[0])
    sim.step(1)
    assert len(calls) == INTERVALS + 1 and calls[-1].interval == 0
    sim.close()
    plain.close()


def test_the_networks_vector_jacobian_product_is_its_jacobians_transpose():
    """``SineNetwork.vjp`` against central differences of ``controls`` in every parameter
    and in the state (its centre included), along random directions, to 1e-8."""
    net = network()
    rng = np.random.default_rng(2)
    n = sheet().n_particles
    state = ControlState(sheet().positions, rng.normal(0, 0.3, (n, 3)), 0.013, 2)
    cotangent = {"rest_lengths": rng.normal(size=SPRINGS.size)}
    params, dx, dv = net.vjp(state, cotangent)

    def along(change):
        e = 1e-6
        ends = []
        for sign in (1, -1):
            trial, where = change(sign * e)
            ends.append(float(cotangent["rest_lengths"] @ trial.controls(where)["rest_lengths"]))
        return (ends[0] - ends[1]) / (2 * e)

    for key in net.parameters:
        d = rng.normal(size=net.parameters[key].shape)

        def change(e, key=key, d=d):
            trial = network()
            trial.parameters[key] = trial.parameters[key] + e * d
            return trial, state
        assert abs(np.sum(params[key] * d) - along(change)) <= 1e-8 * max(1.0, abs(along(change))), key
    for which, exact in (("positions", dx), ("velocities", dv)):
        d = rng.normal(size=(n, 3))

        def change(e, which=which, d=d):
            rows = {"positions": state.positions, "velocities": state.velocities}
            rows[which] = rows[which] + e * d
            return net, ControlState(rows["positions"], rows["velocities"], state.time, state.interval)
        assert abs(np.sum(exact * d) - along(change)) <= 1e-8 * max(1.0, abs(along(change))), which
    assert np.all(dx[[0, 3]] == 0)  # particles it does not watch


@FULL
def test_gradients_through_a_feedback_controller_with_chosen_steps():
    """An error-controlled run chooses the steps (``tol``, ``times``); the gradient of that
    step sequence through the controller against central differences of replayed runs
    with the same steps (the controller choosing again in each)."""
    integrator, options = "implicit", SOLVED["implicit"]
    times = [0.008, 0.02]
    value, grads = ms.gradient(controlled(), objective, ["controller.w1", "velocities"], integrator=integrator,
                               tol=1e-4, times=times, controller=network(), **options)
    sizes = ms.gradients.chosen_steps(controlled(), integrator, 1e-4, np.array(times), 1e-2, None, None, "f64",
                                      dict(controller=network()))
    dts, frames = sizes

    def replayed(model, net):
        sim = ms.Simulation(model, integrator, dt=PER * DT, controller=net, **options)
        positions, velocities = [sim.positions], [sim.velocities]
        for a, b in zip(frames[:-1], frames[1:]):
            sim.replay(dts[a:b])
            positions.append(sim.positions)
            velocities.append(sim.velocities)
        sim.close()
        return objective(ms.Frames(np.array(positions), np.array(velocities), np.array([0.0, *times]), frames))[0]

    assert value == pytest.approx(replayed(controlled(), network()), rel=1e-12)
    rng = np.random.default_rng(4)
    for name in ("controller.w1", "velocities"):
        direction = rng.normal(size=grads[name].shape)
        if name == "velocities":
            direction[PINNED] = 0
        direction /= np.abs(direction).max()
        e = 1e-6 * max(1.0, scale(name))
        numeric = (replayed(*perturbed(name, e, direction)) - replayed(*perturbed(name, -e, direction))) / (2 * e)
        exact = float(np.sum(grads[name] * direction))
        assert abs(exact - numeric) <= 1e-6 * abs(numeric), (name, exact, numeric)


class Broken(ms.Controller):
    """A controller whose answer is given: ``answer`` for every interval."""

    def __init__(self, answer, interval=PER * DT, drives=("rest_lengths",), springs=SPRINGS):
        self.interval, self.drives, self.springs, self.answer = interval, drives, springs, answer
        self.parameters = {"k": np.zeros(2)}

    def controls(self, state):
        return self.answer

    def vjp(self, state, cotangents):
        return {"k": np.zeros(2)}, None, None


def test_bad_controllers_are_refused_naming_what_is_wrong():
    """Before any step: not a controller, a model without controls, another interval,
    controls the model lacks, other springs; gradients asked of what it sets; at the
    interval's start: an answer of the wrong shape or sign."""
    good = {"rest_lengths": np.full(3, 0.1)}
    model = controlled()
    cases = [
        (dict(model=model, controller=object()), "controller: expected a massspring.Controller"),
        (dict(model=sheet(pin_velocity=None), controller=network()), "controller: the model has no controls"),
        (dict(model=model, controller=Broken(good, interval=0.01)), "controller.interval"),
        (dict(model=model, controller=Broken(good, drives=("wind",))), "controller.drives: 'wind'"),
        (dict(model=model, controller=Broken(good, drives=("pin_targets",))), "controller.drives: 'pin_targets'"),
        (dict(model=model, controller=Broken(good, drives=("gravity",))), "controller.drives: expected"),
        (dict(model=model, controller=Broken(good, springs=np.array([0, 5, 8]))), "controller.springs"),
    ]
    for kwargs, message in cases:
        with pytest.raises(ValueError, match=message.replace(".", r"\.").replace("(", r"\(")):
            ms.Simulation(kwargs["model"], "symplectic", dt=DT, controller=kwargs["controller"])
        with pytest.raises(ValueError, match=message.replace(".", r"\.").replace("(", r"\(")):
            ms.gradient(kwargs["model"], objective, "stiffness", steps=2, dt=DT, controller=kwargs["controller"])
    for name, message in (("controls.rest_lengths", "the controller sets it"), ("controller.w9", "unknown parameter"),
                          ("pin_velocity", "pins' motion")):
        with pytest.raises(ValueError, match=message):
            ms.gradient(sheet(controls=network().controls_for(INTERVALS)), objective, name, steps=2, dt=DT,
                        controller=network())
    for answer, message in (({"wind": np.zeros(3)}, "no 'rest_lengths'"),
                            ({"rest_lengths": np.ones(2)}, r"'rest_lengths' at t = 0 s must be \(3,\)"),
                            ({"rest_lengths": -np.ones(3)}, "a rest length < 0"), (None, "expected a dict")):
        sim = ms.Simulation(model, "symplectic", dt=DT, controller=Broken(answer))
        with pytest.raises(ValueError, match="controller.controls: " + message):
            sim.step(1)
        sim.close()


class Pumping(ms.Controller):
    """Two particles' spring made 0.5x then 1.5x its length, interval after interval; with
    ``speed`` as its ``top_speed`` (None: unknown)."""

    drives = ("rest_lengths",)

    def __init__(self, speed):
        self.interval, self.springs, self.speed = 1e-3, np.array([0]), speed
        self.parameters = {}

    def controls(self, state):
        return {"rest_lengths": np.array([0.05 if state.interval % 2 else 0.15])}

    def vjp(self, state, cotangents):
        return {}, None, None

    def top_speed(self):
        return self.speed


def test_the_divergence_check_counts_what_a_controller_drives():
    """A controller pumping a stiff spring puts far more energy in than its model's
    controls (the placeholder, constant rest length) say: with its ``top_speed`` (2 x 0.05
    m a millisecond: 100 m/s) the check's floor counts it and the run goes on; without,
    the check calls the pumped run runaway."""
    model = ms.Model([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]], [[0, 1]], masses=0.01, stiffness=1e4, damping=0.0,
                     gravity=(0.0, 0.0, 0.0), controls=ms.Controls(1e-3, springs=[0], rest_lengths=np.full((40, 1), 0.1)))
    sim = ms.Simulation(model, "symplectic", dt=1e-4, controller=Pumping(100.0))
    sim.step(400)
    assert sim.steps == 400 and np.all(np.isfinite(sim.positions))
    sim.close()
    sim = ms.Simulation(model, "symplectic", dt=1e-4, controller=Pumping(None))
    with pytest.raises(ms.DivergenceError, match="runaway"):
        sim.step(400)
    sim.close()
    with pytest.raises(ValueError, match="controller.top_speed"):
        ms.Simulation(model, "symplectic", dt=1e-4, controller=Pumping(-1.0))
    assert network().top_speed() == pytest.approx(np.max(0.4 * network().rest) / (PER * DT))


class Tug(ms.Controller):
    """Pins set from the state: each interval's targets, P_s = start + b + A f, with f the
    mean position (about the start's) and the mean velocity of every particle, pinned
    ones included (so that the pins' own motion feeds back)."""

    drives = ("pin_targets",)

    def __init__(self):
        rng = np.random.default_rng(2)
        self.interval = PER * DT
        self.start = sheet(pin_velocity=None).positions[PINNED]
        self.centre = sheet(pin_velocity=None).positions.mean(axis=0)
        self.parameters = {"a": rng.normal(0, 0.05, (3, 6)), "b": rng.normal(0, 0.002, (len(PINNED), 3))}

    def features(self, state):
        return np.concatenate([state.positions.mean(axis=0) - self.centre, state.velocities.mean(axis=0)])

    def controls(self, state):
        return {"pin_targets": self.start + self.parameters["b"] + (self.parameters["a"] @ self.features(state))[None]}

    def vjp(self, state, cotangents):
        c = cotangents["pin_targets"].sum(axis=0)
        n = state.positions.shape[0]
        df = self.parameters["a"].T @ c
        return ({"a": np.outer(c, self.features(state)), "b": cotangents["pin_targets"].copy()},
                np.tile(df[:3] / n, (n, 1)), np.tile(df[3:] / n, (n, 1)))


def tugged(**changes):
    start = sheet(pin_velocity=None).positions[PINNED]
    return sheet(pin_velocity=None, controls=ms.Controls(PER * DT, pin_targets=np.repeat(start[None], INTERVALS, axis=0)),
                 **changes)


@pytest.mark.fast_sample(integrator=["symplectic"])
@pytest.mark.parametrize("integrator", KEYFRAMED)
def test_gradients_through_a_controller_that_moves_the_pins(integrator):
    """A controller choosing where the pins go from the state, which the pins' own motion
    changes: the gradient in its parameters, the initial state and the stiffness within
    1e-6 of central differences. The pinned particles' rows of its share of the state's
    adjoint go back through the pins' motion (dropping them, the derivatives were 3% to
    150% off, measured on the symplectic run)."""
    options = SOLVED.get(integrator, {})
    names = ["controller.a", "controller.b", "positions", "velocities", "stiffness"]
    _, grads = ms.gradient(tugged(), objective, names, integrator=integrator, controller=Tug(), **RUN, **options)
    rng = np.random.default_rng(0)
    for name in names:
        direction = rng.normal(size=grads[name].shape)
        if name in ("positions", "velocities"):
            direction[PINNED] = 0
        direction /= np.abs(direction).max()
        key = name.split(".", 1)[-1]
        size = np.abs(Tug().parameters[key] if name.startswith("controller.") else getattr(tugged(), name)).max()
        eps = STEP.get(integrator, 1e-6) * max(1.0, size)

        def moved(e):
            tug = Tug()
            if name.startswith("controller."):
                tug.parameters[key] = tug.parameters[key] + e * direction
                return tugged(), tug
            return tugged(**{name: getattr(tugged(), name) + e * direction}), tug

        def central(e):
            return (run_value(*moved(e), integrator, options) - run_value(*moved(-e), integrator, options)) / (2 * e)

        numeric = central(eps) if integrator not in STEP else (4 * central(eps) - central(2 * eps)) / 3
        exact = float(np.sum(grads[name] * direction))
        assert abs(exact - numeric) <= 1e-6 * abs(numeric), (name, exact, numeric)


def test_pins_a_controller_moves_reach_its_targets_as_keyframed_pins_do():
    """The pins reach each target the controller chose at its interval's end and move at
    (P_s - P_s-1) / T over it: from the end of the first step on, the run equals to the
    bit the open-loop run of those targets set to that state (``set_state`` checks a
    pin's velocity against the one it last moved with: the chosen one). At the start a pin
    has the model's pin velocity, the placeholders' (here 0), which the controller reads."""
    tug = Tug()
    sim = ms.Simulation(tugged(), "symplectic", dt=DT, controller=tug)
    assert np.all(sim.velocities[PINNED] == 0)
    sim.step(1)
    first = (sim.positions, sim.velocities)
    sim.step(PER * INTERVALS - 1)
    chosen = np.array([tug.controls(sim.control_states[s])["pin_targets"] for s in range(INTERVALS)])
    assert np.abs(sim.positions[PINNED] - chosen[-1]).max() <= 1e-15
    assert np.abs(chosen - tug.start).max() > 1e-3  # the pins moved
    assert np.allclose(first[1][PINNED], (chosen[0] - tug.start) / (PER * DT), rtol=1e-12)
    plain = ms.Simulation(sheet(pin_velocity=None, controls=ms.Controls(PER * DT, pin_targets=chosen)), "symplectic",
                          dt=DT)
    plain.set_state(*first, steps=1)
    plain.step(PER * INTERVALS - 1)
    assert np.array_equal(plain.positions, sim.positions) and np.array_equal(plain.velocities, sim.velocities)
    sim.close()
    plain.close()


def test_a_controller_moving_the_pins_of_a_renumbered_model(monkeypatch):
    """A scrambled sheet that the run renumbers, with the pin-moving controller: its pin
    rows follow the renumbering, so the value and the gradients are the sheet's own (the
    targets' rows permuted)."""
    from massspring.model import ordering

    monkeypatch.setattr(ordering, "WINDOW", 4)
    model = tugged()
    rng = np.random.default_rng(0)  # the pins' rows swap
    particles, springs = rng.permutation(model.n_particles), rng.permutation(model.n_springs)
    inverse = np.argsort(particles)
    rows = np.argsort(inverse[PINNED])  # the sheet's pin rows in the scrambled model's order of pins
    scrambled = ms.Model(model.positions[particles], inverse[model.springs][springs], masses=model.masses[particles],
                         stiffness=model.stiffness[springs], damping=model.damping[springs],
                         rest_lengths=model.rest_lengths[springs], velocities=model.velocities[particles],
                         gravity=model.gravity, fixed=inverse[PINNED], drag=model.drag, wind=model.wind,
                         controls=ms.Controls(PER * DT, pin_targets=model.controls.pin_targets[:, rows]))
    plan = ordering.plan(scrambled)
    assert plan is not None and list(rows) == [1, 0]
    tug = Tug()
    tug.start, tug.parameters["b"] = tug.start[rows], tug.parameters["b"][rows]

    def scrambled_objective(frames):
        value, partials = objective(type(frames)(frames.positions[:, inverse], frames.velocities[:, inverse],
                                                 frames.times, frames.steps))
        return value, {key: rows_[:, particles] for key, rows_ in partials.items()}

    names = ["controller.a", "controller.b", "stiffness"]
    want_value, want = ms.gradient(model, objective, names, controller=Tug(), **RUN)
    got_value, got = ms.gradient(scrambled, scrambled_objective, names, controller=tug, **RUN)
    assert got_value == pytest.approx(want_value, rel=1e-12)
    got["controller.b"][rows] = got["controller.b"].copy()
    got["stiffness"] = got["stiffness"][np.argsort(springs)]
    for name in names:
        assert np.allclose(got[name], want[name], rtol=1e-9, atol=1e-12 * np.abs(want[name]).max()), name
