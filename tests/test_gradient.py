"""Gradients through the steps (``massspring.gradient``, issue 39): directional
derivatives against central differences of the forward runs, exact discrete
gradients of a falling particle, checkpointing, and arguments refused before any step."""

import dataclasses

import numpy as np
import pytest

import massspring as ms
from conftest import FULL, PATHS
from massspring.support.errors import GradientError
from massspring.gradients import PARAMETERS as ALL_PARAMETERS, differentiable

# conftest: Taichi is reset after a test that leaves this process above 1 GB (each test
# compiles the adjoints of its own configuration and shares no simulation)
RESET_BETWEEN_TESTS = 1.0e9
DIFFERENTIABLE = differentiable()
# The model's (test_controls: the rest), in the order the tests' random directions were drawn in
# when they were written (each name draws its direction from one generator in turn); a new name comes last.
FIRST = ("stiffness", "damping", "rest_lengths", "masses", "positions", "velocities", "gravity", "drag", "wind",
         "pin_velocity")
PARAMETERS = sorted((name for name, kind in ALL_PARAMETERS.items() if kind != "control"),
                    key=lambda name: FIRST.index(name) if name in FIRST else len(FIRST))
STILL_AIR = [name for name in PARAMETERS if name not in ("drag", "wind", "pin_velocity")]  # of a model without drag and pins
SIDE = 4  # a 4 x 4 sheet with shear springs: 16 particles, 33 springs
PINNED = [0, SIDE - 1]


def sheet_grid(side=3):
    """A flat side x side sheet of spacing 0.1 m at z = 0: positions (n, 3) and its
    structural and shear springs (one diagonal a square)."""
    positions = np.array([[i * 0.1, j * 0.1, 0.0] for j in range(side) for i in range(side)])
    springs = []
    for j in range(side):
        for i in range(side):
            a = j * side + i
            springs += [[a, a + 1]] * (i + 1 < side) + [[a, a + side]] * (j + 1 < side)
            springs += [[a, a + side + 1]] * (i + 1 < side and j + 1 < side)
    return positions, springs


def sheet(seed=1, damped=True, **changes):
    """A jittered sheet pinned at two corners (one pin moving; a pin starts at its pin
    velocity), damped, with random per-item parameters, a tilted gravity, air drag and
    wind: every parameter kind differs from item to item."""
    rng = np.random.default_rng(seed)
    positions, springs = sheet_grid(SIDE)
    positions += rng.normal(0, 0.01, positions.shape)
    n, m = len(positions), len(springs)
    values = dict(positions=positions, masses=rng.uniform(0.5, 1.5, n), stiffness=rng.uniform(50, 150, m),
                  damping=rng.uniform(0.1, 1.0, m) if damped else np.zeros(m),
                  rest_lengths=rng.uniform(0.08, 0.12, m), velocities=rng.normal(0, 0.1, (n, 3)),
                  gravity=np.array([0.1, -0.2, -9.8]), drag=0.3, wind=np.array([1.0, 0.5, -0.2]),
                  pin_velocity=np.array([[0, 0, 0.1], [0, 0, 0]]))
    values.update(changes)
    return ms.Model(values.pop("positions"), springs, fixed=PINNED, **values)


def weights(frames_count, n, seed=7):
    return np.random.default_rng(seed).normal(size=(frames_count, n, 3))


def objective(frames):
    """L = sum C . X + |V|^2 / 2 over the frames: dL/dX = C, dL/dV = V."""
    c = weights(len(frames.positions), frames.positions.shape[1])
    value = np.sum(c * frames.positions) + 0.5 * np.sum(frames.velocities ** 2)
    return value, {"positions": c, "velocities": frames.velocities}


RUN = dict(steps=10, every=2, dt=2e-3, checkpoint=3)
# Solver options per integrator: the gradient is that of the step as solved, so the
# implicit step's CG solves (forward and adjoint) to round-off here
NEWTON_SOLVED = dict(cg_tol=1e-13, newton_tol=1e-12, newton_max_iter=200)
SOLVED = {"implicit": dict(cg_tol=1e-13), "backward-euler": NEWTON_SOLVED, "bdf2": NEWTON_SOLVED,
          "midpoint": NEWTON_SOLVED}
# Central differences' step, relative to the largest value: a Newton-solved run meets its
# equations to about 1e-13 relative of the value, noise that a step of 1e-6 lifts above
# 1e-6 of a small derivative (measured on the damping of the midpoint run: 3e-6 at 1e-5,
# 2e-4 at 1e-6); so a step of 1e-3 there, and Richardson's combination of the steps eps
# and 2 eps, whose error is O(eps^4) (4e-8 at most measured, every parameter)
STEP = {"backward-euler": 1e-3, "bdf2": 1e-3, "midpoint": 1e-3}


def run_value(model, objective, run):
    """The objective of a plain forward run with the options of ``run`` (what
    ``ms.gradient`` would take): a Simulation stepped to each frame, no backward pass."""
    options = {k: v for k, v in run.items() if k not in ("steps", "every", "checkpoint", "integrator", "dt")}
    steps, every = run["steps"], run.get("every", 1)
    sim = ms.Simulation(model, run.get("integrator", "symplectic"), dt=run.get("dt", 1e-2), **options)
    positions, velocities, at = [], [], list(range(0, steps + 1, every))
    try:
        for k in at:
            sim.step(k - sim.steps)
            positions.append(sim.positions)
            velocities.append(sim.velocities)
    finally:
        sim.close()
    at = np.array(at)
    return objective(ms.Frames(np.array(positions), np.array(velocities), at * sim.dt, at))[0]


def directional_difference(make, values, name, direction, integrator, run):
    """The derivative of the run's objective along ``direction`` (its largest entry 1) in
    parameter ``name``: central differences (``STEP``), Richardson-combined for the
    Newton-solved integrators."""
    eps = STEP.get(integrator, 1e-6) * max(1.0, np.abs(values[name]).max())

    def central(e):
        ends = [run_value(make(**dict(values, **{name: values[name] + sign * e * direction})), objective, run)
                for sign in (1, -1)]
        return (ends[0] - ends[1]) / (2 * e)

    if integrator not in STEP:
        return central(eps)
    return (4 * central(eps) - central(2 * eps)) / 3


def unit_direction(rng, values, name):
    """A random direction of parameter ``name``, its largest entry 1 in size; zero at the
    pins' rows of the state (a pin's state is not free: its velocity is its pin's)."""
    direction = rng.normal(size=np.shape(values[name]))
    if name in ("positions", "velocities"):
        direction[PINNED] = 0
    return direction / np.abs(direction).max()


def run_of(integrator, **more):
    return dict(RUN, integrator=integrator, **SOLVED.get(integrator, {}), **more)


def model_values(model):
    return dict(positions=model.positions, masses=model.masses, stiffness=model.stiffness, damping=model.damping,
                rest_lengths=model.rest_lengths, velocities=model.velocities, gravity=model.gravity,
                drag=np.float64(model.drag), wind=model.wind, pin_velocity=model.pin_velocity)


@pytest.mark.fast_sample(integrator=["implicit"], path=["serial"])
@pytest.mark.parametrize("integrator", DIFFERENTIABLE)
@pytest.mark.parametrize("path", PATHS)
def test_directional_derivatives_match_central_differences(integrator, path):
    """Every parameter kind on a pinned (one pin moving), damped sheet under gravity: the
    gradient's directional derivative along a random direction agrees with a central
    difference of the forward runs (``directional_difference``) to 1e-6 relative."""
    model = sheet()
    names = list(PARAMETERS)
    run = run_of(integrator, loops=path)
    value, grads = ms.gradient(model, objective, names, **run)
    values = model_values(model)
    rng = np.random.default_rng(3)
    for name in names:
        assert grads[name].shape == np.shape(values[name]), name
        if name in ("positions", "velocities"):
            assert np.all(grads[name][PINNED] == 0)
        direction = unit_direction(rng, values, name)
        numeric = directional_difference(sheet, values, name, direction, integrator, run)
        exact = float(np.sum(grads[name] * direction))
        assert abs(exact - numeric) <= 1e-6 * abs(numeric), (name, exact, numeric)
    assert value == ms.gradient(model, objective, "gravity", **run)[0] == run_value(model, objective, run)


@FULL
@pytest.mark.parametrize("integrator", DIFFERENTIABLE)
def test_damping_gradient_of_an_undamped_model(integrator):
    """kd = 0 everywhere compiles no damping term; its gradient is still that of the runs
    with a little damping (one-sided differences at kd = e, 2 e and 3 e, ``STEP``)."""
    model = sheet(damped=False)
    run = run_of(integrator)
    grads = ms.gradient(model, objective, ["damping"], **run)[1]
    direction = np.random.default_rng(5).uniform(0.5, 1.0, model.n_springs)
    values = model_values(model)
    # a negative damping is refused by the Model: the one-sided four-point formula, whose
    # error is O(eps^3) (the three-point one's O(eps^2) is 3e-5 relative at STEP's 1e-3)
    e = STEP.get(integrator, 1e-6)
    ends = [run_value(sheet(**dict(values, damping=k * e * direction)), objective, run) for k in (1, 2, 3)]
    base = run_value(model, objective, run)
    numeric = (-11 * base + 18 * ends[0] - 9 * ends[1] + 2 * ends[2]) / (6 * e)
    exact = float(np.sum(grads["damping"] * direction))
    assert abs(exact - numeric) <= 1e-6 * abs(numeric), (exact, numeric)


@pytest.mark.fast_sample(integrator=["symplectic"])
@pytest.mark.parametrize("integrator, before", [("explicit", -1), ("symplectic", 1), ("implicit", 1), ("rk4", 0),
                                                ("backward-euler", 1), ("midpoint", 0)])
def test_a_falling_particle_has_its_exact_discrete_gradient(integrator, before):
    """One free particle under gravity, L = z after N steps: explicit Euler gives
    z_N = z_0 + N h v_0 + h^2 g N (N - 1) / 2, symplectic, implicit and backward Euler
    (A = M: the same step) N (N + 1) / 2 in place of N (N - 1) / 2, RK4 and implicit
    midpoint (exact for a constant acceleration) N^2 / 2, so dL/dz_0 = 1, dL/dv_0 = N h, dL/dg = h^2 N (N + c) / 2 (c = -1, 1, 0)."""
    steps, h = 7, 0.01
    model = ms.Model([[0.0, 0.0, 1.0]], np.zeros((0, 2), int), masses=2.0, velocities=[[0.3, 0.0, 0.5]])

    def height(frames):
        partial = np.zeros_like(frames.positions)
        partial[-1, 0, 2] = 1.0
        return frames.positions[-1, 0, 2], {"positions": partial}

    value, grads = ms.gradient(model, height, ["positions", "velocities", "gravity", "masses"], steps=steps,
                               dt=h, integrator=integrator, every=steps, **SOLVED.get(integrator, {}))
    g = model.gravity[2]
    assert value == pytest.approx(1.0 + steps * h * 0.5 + h * h * g * steps * (steps + before) / 2, rel=1e-14)
    np.testing.assert_allclose(grads["positions"], [[0, 0, 1]], rtol=1e-14)
    np.testing.assert_allclose(grads["velocities"], [[0, 0, steps * h]], rtol=1e-14)
    np.testing.assert_allclose(grads["gravity"], [0, 0, h * h * steps * (steps + before) / 2], rtol=1e-14)
    # gravity's acceleration does not depend on the mass: zero, to the round-off of the explicit steps' f / m
    # taken from the kept velocities, (v' - v) / h (``euler.adjoint_step``; measured 1.6e-18 here)
    assert abs(grads["masses"][0]) <= 1e-14 * abs(grads["gravity"][2])


@pytest.mark.fast_sample(integrator=["symplectic"])
@pytest.mark.parametrize("integrator", DIFFERENTIABLE)
def test_checkpointed_gradients_equal_those_of_the_stored_trajectory(integrator):
    """Every state kept (checkpoint 1), one kept (checkpoint = steps) and the default give
    the same value and gradients to the bit: a stretch run again from its checkpoint
    repeats the forward run's bits (a restart continues bitwise)."""
    model = sheet()
    results = [ms.gradient(model, objective, list(PARAMETERS), steps=12, every=3, dt=2e-3, integrator=integrator,
                           checkpoint=k, **SOLVED.get(integrator, {})) for k in (1, 12, None, 5)]
    for value, grads in results[1:]:
        assert value == results[0][0]
        for name in PARAMETERS:
            np.testing.assert_array_equal(grads[name], results[0][1][name])


@pytest.mark.fast_sample(integrator=["symplectic"])
@pytest.mark.parametrize("integrator", ["explicit", "symplectic"])
def test_steps_run_backwards_in_one_launch_give_the_step_by_step_bits(integrator, monkeypatch):
    """The explicit steps' adjoints between frames run in one launch (``adjoint_steps``):
    the same value and gradients, to the bit, as one launch a step; and the masses'
    gradient taken from the kept velocities is the one from the forces computed again."""
    from massspring.integrators.explicit import ExplicitEuler

    model = sheet()

    def run():
        return ms.gradient(model, objective, list(PARAMETERS), steps=12, every=5, dt=2e-3, integrator=integrator,
                           checkpoint=7, loops="serial")

    together = run()
    monkeypatch.setattr(ExplicitEuler, "adjoint_steps", lambda self, *args: False)
    apart = run()
    monkeypatch.setattr(ExplicitEuler, "_masses", lambda self, wants: (wants, False))
    forces = run()
    assert together[0] == apart[0]
    for name in PARAMETERS:
        np.testing.assert_array_equal(together[1][name], apart[1][name])
        if name != "masses":
            np.testing.assert_array_equal(together[1][name], forces[1][name])
    scale = np.abs(forces[1]["masses"]).max()
    gap = np.abs(together[1]["masses"] - forces[1]["masses"]).max()
    assert scale > 0 and gap <= 1e-13 * scale  # measured 2.5e-16 (explicit) and 4.9e-16 (symplectic)


@pytest.mark.fast_sample(integrator=["symplectic"])
@pytest.mark.parametrize("integrator", ["explicit", "symplectic"])
def test_steps_with_controls_and_a_ground_run_backwards_in_one_launch_a_control_interval(integrator, monkeypatch):
    """Issue 60 (the creature's gradient cost 14x its run, one adjoint launch a step):
    with controls (wind, rest lengths and pins per interval of 3 steps) and a still ground
    with friction that the sheet lands on, the explicit steps' adjoints run in one launch
    per stretch within a control interval; the same value and gradients, to the bit, as
    one launch a step."""
    from massspring.integrators.explicit import ExplicitEuler
    from test_controls import control_values, controlled

    ground = ms.Plane((0.0, 0.0, -0.0075), (0.0, 0.0, 1.0), friction=0.5)
    fall = dict(control_values(), gravity=np.array([0.0, 0.0, -30.0]))
    model = controlled(**fall, colliders=[ground])
    names = ["stiffness", "masses", "positions", "controls.wind", "controls.rest_lengths", "controls.pin_targets"]

    def run(m=model):
        return ms.gradient(m, objective, names, steps=12, every=4, dt=2e-3, integrator=integrator, checkpoint=7,
                           loops="serial")

    launches = []
    batched = ExplicitEuler.adjoint_steps
    monkeypatch.setattr(ExplicitEuler, "adjoint_steps", lambda self, *a: launches.append(a[2]) or batched(self, *a))
    together = run()
    assert len(launches) >= 3 and max(launches) == 3  # a control interval's steps in one launch
    monkeypatch.setattr(ExplicitEuler, "adjoint_steps", lambda self, *args: False)
    apart = run()
    assert together[0] == apart[0] != run(controlled(**fall))[0]  # the ground acts
    for name in names:
        np.testing.assert_array_equal(together[1][name], apart[1][name])


@pytest.mark.fast_sample(integrator=["symplectic"])
@pytest.mark.parametrize("integrator, checkpoint", [("symplectic", None), ("symplectic", 2), ("explicit", 4),
                                                    ("rk4", None)])
def test_frames_are_the_run_at_every_kth_step(integrator, checkpoint):
    """The objective sees frame 0 and every ``every``-th step of the run a Simulation takes
    (the frames of the last stretch read from the history the serial explicit kernels record)."""
    model = sheet()
    seen = {}

    def keep(frames):
        seen["frames"] = frames
        return 0.0, {}

    value, grads = ms.gradient(model, keep, ["stiffness"], steps=7, every=3, dt=2e-3, integrator=integrator,
                               checkpoint=checkpoint)
    frames = seen["frames"]
    assert value == 0.0 and np.all(grads["stiffness"] == 0)
    np.testing.assert_array_equal(frames.steps, [0, 3, 6])
    np.testing.assert_allclose(frames.times, [0, 6e-3, 12e-3], rtol=1e-15)
    sim = ms.Simulation(model, integrator, dt=2e-3)
    for f, k in enumerate(frames.steps):
        sim.step(int(k) - sim.steps)
        np.testing.assert_array_equal(frames.positions[f], sim.positions)
        np.testing.assert_array_equal(frames.velocities[f], sim.velocities)
    sim.close()


def test_an_integrator_without_an_adjoint_is_refused_by_name(monkeypatch):
    """Every integrator has one now; one that had none would be refused naming those that do."""
    from massspring.integrators import INTEGRATORS

    monkeypatch.setattr(INTEGRATORS["rk4"], "traits", dataclasses.replace(INTEGRATORS["rk4"].traits,
                                                                          differentiable=False))
    with pytest.raises(ValueError, match=r"integrator: gradients through 'rk4' steps are not built yet; they are "
                                         r"for: explicit, symplectic, implicit, backward-euler, bdf2, midpoint"):
        ms.gradient(sheet(), objective, "stiffness", steps=2, integrator="rk4")


@pytest.mark.parametrize("kwargs, words", [
    (dict(wrt="bogus"), ["wrt", "unknown parameter 'bogus'", "stiffness"]),
    (dict(wrt="pin_velocity", model=ms.Model([[0, 0, 0], [1, 0, 0]], [[0, 1]])), ["wrt", "'pin_velocity'", "no pins"]),
    (dict(wrt="wind", model=sheet(drag=0.0, wind=np.zeros(3))), ["wrt", "'wind'", "no air drag"]),
    (dict(wrt=["masses", "masses"]), ["wrt", "twice"]),
    (dict(wrt=[]), ["wrt", "expected a name"]),
    (dict(integrator="leapfrog"), ["integrator", "leapfrog"]),
    (dict(precision="f32"), ["precision", "f64"]),
    (dict(steps=0), ["steps"]),
    (dict(every=0), ["every"]),
    (dict(checkpoint=0), ["checkpoint"]),
    (dict(objective=3), ["objective", "function"]),
    (dict(model=None), ["model", "massspring.Model"]),
])
def test_bad_arguments_are_refused_before_any_step(kwargs, words):
    calls = []

    def counted(frames):
        calls.append(frames)
        return 0.0, {}

    args = dict(model=sheet(), objective=counted, wrt="stiffness", steps=3, dt=1e-3, integrator="symplectic")
    args.update(kwargs)
    with pytest.raises(ValueError) as info:
        ms.gradient(args.pop("model"), args.pop("objective"), args.pop("wrt"), **args)
    for word in words:
        assert word in str(info.value), (word, str(info.value))
    assert not calls


def sheet_values(rng, positions, velocities, m):
    """The random per-particle and per-spring values of the contact tests' sheets."""
    n = len(positions)
    return dict(positions=positions, masses=rng.uniform(0.5, 1.5, n), stiffness=rng.uniform(50, 150, m),
                damping=rng.uniform(0.1, 1, m), rest_lengths=rng.uniform(0.09, 0.11, m), velocities=velocities,
                gravity=np.array([0.0, 0.0, -9.8]))


def two_sheets(gap, thickness, thrown=0.0, seed=4, **changes):
    """Two 3 x 3 damped sheets with shear springs, ``gap`` (m) apart in z, falling and
    moving sideways together at 3 m/s (farther a step than the pass's free distances:
    it runs in full every step), with random per-item values and triangles; the upper
    one moving down at ``thrown`` m/s more."""
    rng = np.random.default_rng(seed)
    positions, springs = sheet_grid()
    triangles = [[a, a + 1, a + 4] for a in (0, 1, 3, 4)] + [[a, a + 4, a + 3] for a in (0, 1, 3, 4)]
    positions = np.vstack([positions, positions + [0.0, 0.0, gap]])
    springs = springs + [[a + 9, b + 9] for a, b in springs]
    triangles = triangles + [[a + 9, b + 9, c + 9] for a, b, c in triangles]
    values = sheet_values(rng, positions, rng.normal(0, 0.05, (18, 3)), len(springs))
    values["velocities"][:, 0] += 3.0
    values["velocities"][9:, 2] -= thrown
    values.update(changes)
    return ms.Model(values.pop("positions"), springs, triangles=triangles, **values)


SHEETS_RUN = dict(steps=10, every=5, dt=2e-3, checkpoint=4)


@pytest.mark.fast_sample(integrator=["symplectic"])
@pytest.mark.parametrize("integrator", ["symplectic", "implicit", "backward-euler"])
def test_self_collision_that_changes_nothing_leaves_the_gradient(integrator):
    """Two sheets 5 cm apart moving together, self-collision thickness 1 cm: the pass runs
    in full every step but never acts (no pair within the thickness, none closing too
    fast), so the run and its
    gradient, every parameter kind, are those of the same sheets without self-collision
    (whose gradients the tests above check against differences). One integrator of each
    way a step meets the pass (an explicit step recording its history in the launch, the
    linearised step with the pairs in its solve, a Newton-solved step); the others' pass
    acting is checked against differences below."""
    run = dict(SHEETS_RUN, integrator=integrator, **SOLVED.get(integrator, {}))
    names = [name for name in PARAMETERS if name not in ("drag", "wind", "pin_velocity")]
    model = two_sheets(0.05, 0.01, self_collision=ms.SelfCollision(0.01))
    sim = ms.Simulation(model, integrator, dt=run["dt"])
    sim.step(run["steps"])
    assert sim.self_collision_stats["passes"] == run["steps"] and sim.self_collision_stats["repelled"] == 0
    sim.close()
    value, grads = ms.gradient(model, objective, names, **run)
    plain_value, plain = ms.gradient(two_sheets(0.05, 0.01), objective, names, **run)
    assert value == pytest.approx(plain_value, rel=1e-13)
    for name in names:
        np.testing.assert_allclose(grads[name], plain[name], rtol=1e-10, atol=1e-13 * np.abs(plain[name]).max(),
                                   err_msg=name)


@pytest.mark.fast_sample(integrator=["implicit"])
@pytest.mark.parametrize("integrator", ["symplectic", "implicit", "backward-euler"])
def test_gradients_through_colliding_sheets_are_finite(integrator):
    """The upper sheet thrown at the lower one at 4 m/s (3 cm apart, thickness 1 cm), and
    sheets starting at half the thickness (with the linearised step, pairs in its solve
    from step 1): the pass repels, pushes and holds back particles, and the gradient is
    returned, finite."""
    run = dict(SHEETS_RUN, integrator=integrator, **SOLVED.get(integrator, {}))
    for model in (two_sheets(0.03, 0.01, thrown=4.0, self_collision=ms.SelfCollision(0.01)),
                  two_sheets(0.005, 0.01, self_collision=ms.SelfCollision(0.01))):
        sim = ms.Simulation(model, integrator, dt=run["dt"])
        acted = 0
        for _ in range(run["steps"]):
            sim.step(1)
            acted += sim.self_collision_stats["repelled"] + sim.self_collision_stats["bounded"]
        sim.close()
        assert acted > 0
        value, grads = ms.gradient(model, objective, "stiffness", **run)
        assert np.isfinite(value) and np.all(np.isfinite(grads["stiffness"]))


def straddling(friction=0.05, k_r=1e5, seed=5, **changes):
    """A small triangle 7 mm over a square of two triangles (thickness 1 cm), straddling
    their shared edge, sliding sideways at 0.3 m/s, both falling: every step the pass
    repels its corners from the face below them and its two edges crossing the shared
    one (face and inside regions, the closest points 1.5 cm and more from their
    regions' borders, the pairs' distances 3 mm and more from the thickness), with
    friction ``friction``, the repulsion stiffness ``k_r`` (N/m; None: the springs'
    median); its springs stretched (rest lengths 5-15% short) so that each parameter
    kind moves the run. Random per-item values."""
    rng = np.random.default_rng(seed)
    lower = np.array([[0, 0, 0], [0.3, 0, 0], [0.3, 0.3, 0], [0, 0.3, 0]], float)
    angles = np.array([0.3, 2.5, 4.4])
    upper = [0.15, 0.15, 0.007] + 0.045 * np.stack([np.cos(angles), np.sin(angles), 0 * angles], axis=1)
    positions = np.vstack([lower, upper])
    springs = np.array([[0, 1], [1, 2], [2, 3], [3, 0], [0, 2], [4, 5], [5, 6], [6, 4]])
    velocities = rng.normal(0, 0.05, (7, 3)) + np.array([[0.0, 0.0, 0.0]] * 4 + [[0.3, 0.0, 0.0]] * 3)
    lengths = np.linalg.norm(positions[springs[:, 0]] - positions[springs[:, 1]], axis=1)
    values = dict(positions=positions, masses=rng.uniform(0.5, 1.5, 7), stiffness=rng.uniform(50, 150, 8),
                  damping=rng.uniform(0.1, 1, 8), rest_lengths=lengths * rng.uniform(0.85, 0.95, 8),
                  velocities=velocities, gravity=np.array([0.0, 0.0, -9.8]))
    values.update(changes)
    return ms.Model(values.pop("positions"), springs, triangles=[[0, 1, 2], [0, 2, 3], [4, 5, 6]],
                    self_collision=ms.SelfCollision(0.01, friction=friction, stiffness=k_r), **values)


def richardson_difference(make, values, name, direction, run, eps):
    """Central differences of the runs at steps eps and 2 eps, Richardson-combined."""
    def central(e):
        ends = [run_value(make(**{name: values[name] + sign * e * direction}), objective, run) for sign in (1, -1)]
        return (ends[0] - ends[1]) / (2 * e)

    return (4 * central(eps) - central(2 * eps)) / 3


STRADDLING_RUN = dict(steps=10, every=5, dt=2e-3, checkpoint=4)
# The pass sums its impulses in fixed point (2^-40 m/s): runs that differ by a step of
# 1e-5 of a parameter differ by its rounding too, which lifts the central differences'
# error to 4e-6 of the smaller derivatives (measured), so the parameters step 1e-4 of
# their largest value and damping, whose derivative is the smallest here (3e-9 noise in
# 1e-3 measured at 1e-4), 1e-3; the initial state steps 1e-5 m (m/s), which moves the
# pairs' normal speeds by 1e-5 / dt, within the branches of the step as taken
STRADDLING_STEP = {"positions": 1e-5, "velocities": 1e-5, "damping": 1e-3}
# The linearised step's solve holds the pairs, whose penalty friction the pass sums in
# fixed point too: with sticking friction its differences' error falls as 1 / step
# (measured on damping: 2.3e-6, 1.3e-6, 4.0e-7, 2.0e-8 at 1e-4, 1e-3, 1e-2, 3e-2; on
# stiffness 4.2e-7, 3.6e-8, 1.1e-8 at 1e-4, 1e-3, 1e-2), so these two take larger steps
STICKING_PENALTY_STEP = {"stiffness": 1e-2, "damping": 3e-2}
# The repelled triangle's runs carry the pass's fixed-point rounding (1e-12 m), noise that
# a difference step divides: at 1e-5 in the state the worst of the 14 cases below sat at
# 0.79 of the 1e-6 bound (BDF2, sticking, velocities; issue 60 met one at its edge on an
# AMD EPYC), at 2e-5 0.32 (every case, measured on the Intel Xeon; truncation is O(eps^4))
REPULSION_STEP = dict(STRADDLING_STEP, positions=2e-5, velocities=2e-5)


@pytest.mark.fast_sample(integrator=["symplectic"], friction=[0.05])
@pytest.mark.parametrize("friction", [0.05, 5.0])
@pytest.mark.parametrize("integrator", DIFFERENTIABLE)
def test_gradients_through_self_collision_repulsion_match_differences(integrator, friction):
    """The straddling triangle repelled every step, friction sliding (0.05) or sticking
    (5): the gradient of every parameter kind against central differences of the runs,
    to 1e-6 relative. The linearised implicit step also holds the pairs within the
    thickness at a step's start in its solve (penalty springs), whose friction the pass
    adds: leaving out either's share of the gradient fails this by 2e-2 to 1 (measured)."""
    run = dict(STRADDLING_RUN, integrator=integrator, **SOLVED.get(integrator, {}))
    names = STILL_AIR
    model = straddling(friction)
    sim = ms.Simulation(model, integrator, dt=run["dt"])
    sim.step(1)
    assert sim.self_collision_stats["repelled"] >= 4  # (each full pass's count: three corners, two edges)
    sim.close()
    value, grads = ms.gradient(model, objective, names, **run)
    values = model_values(model)
    rng = np.random.default_rng(3)

    def make(**changes):
        return straddling(friction, **changes)

    for name in names:
        direction = rng.normal(size=np.shape(values[name]))
        direction /= np.abs(direction).max()
        steps = dict(REPULSION_STEP, **(STICKING_PENALTY_STEP if integrator == "implicit" and friction > 1 else {}))
        eps = steps.get(name, 1e-4) * max(1.0, np.abs(values[name]).max())
        numeric = richardson_difference(make, values, name, direction, run, eps)
        exact = float(np.sum(grads[name] * direction))
        assert abs(exact - numeric) <= 1e-6 * abs(numeric), (name, exact, numeric)


def thrown_straddling(**changes):
    """The straddling triangle 2-4 cm over the square (tilted), thrown at it at 5 m/s, with
    damping of 1-10 N s/m: in its third step of 2 ms it closes faster than the pass
    allows, and the pass sets pairs to bound their particles (two of its corners pushed
    back, then held back to 0.81 and 0.84 of their displacements) as it repels them; in
    its fifth, a corner is pushed back."""
    model = straddling(0.05)
    positions, velocities = model.positions.copy(), model.velocities.copy()
    positions[4:, 2] = [0.02, 0.03, 0.04]
    velocities[4:, 2] -= 5.0
    return straddling(0.05, **{"positions": positions, "velocities": velocities, "damping": 10 * model.damping,
                               **changes})


@pytest.mark.fast_sample(integrator=["symplectic"])
@pytest.mark.parametrize("integrator", DIFFERENTIABLE)
def test_gradients_through_self_collision_bounds_match_differences(integrator):
    """The thrown triangle over 5 steps, repelled, pushed back and held back: every
    parameter kind against Richardson-combined central differences, to 1e-6 relative.
    The impact lifts the pass's fixed-point rounding (2^-40 m/s) in the runs' values to
    about 1e-10, whose share in a difference falls as its step grows, so each kind takes
    the largest step that keeps the run's branches (measured: larger ones move the
    impact); damping's derivative (1e-4 to 5e-4 here) stays noisy even at 1e-1 of its
    largest value (the differences' error 2e-4, 4e-5, 3e-6 at steps of 1e-3, 1e-2, 1e-1:
    the rounding, falling as 1 / step), so it is held to 1e-5. Leaving out the scales'
    dependence on the positions, or the push's, fails it by 1e-3 to 1e-1. The linearised
    step's runs move the impact at position steps of 1e-5 (a relative error of 0.5;
    3.7e-8 at 1e-6) and rest length steps of 1e-2 (3e-2; 2.4e-7 at 1e-3, 2.8e-6 at 1e-5,
    the rounding): there those two take 1e-6 and 1e-3."""
    run = dict(steps=5, every=1, dt=2e-3, checkpoint=2, integrator=integrator, **SOLVED.get(integrator, {}))
    names = STILL_AIR
    model = thrown_straddling()
    sim = ms.Simulation(model, integrator, dt=run["dt"])
    sim.step(3)
    stats = sim.self_collision_stats
    assert stats["repelled"] > 0 and stats["bounded"] > 0 and stats["held"] > 0
    sim.close()
    value, grads = ms.gradient(model, objective, names, **run)
    values = model_values(model)
    rng = np.random.default_rng(3)
    steps = {"positions": 1e-5, "velocities": 1e-4, "masses": 1e-3, "rest_lengths": 1e-2, "gravity": 1e-2,
             "stiffness": 1e-1, "damping": 1e-1}
    if integrator == "implicit":
        steps.update(positions=1e-6, rest_lengths=1e-3)
    for name in names:
        direction = rng.normal(size=np.shape(values[name]))
        direction /= np.abs(direction).max()
        eps = steps[name] * max(1.0, np.abs(values[name]).max())
        numeric = richardson_difference(thrown_straddling, values, name, direction, run, eps)
        exact = float(np.sum(grads[name] * direction))
        tolerance = 1e-5 if name == "damping" else 1e-6
        assert abs(exact - numeric) <= tolerance * abs(numeric), (name, exact, numeric)


@pytest.mark.fast_sample(integrator=["symplectic"])
@pytest.mark.parametrize("integrator", ["symplectic", "implicit"])
def test_the_repulsion_stiffness_as_the_springs_median_has_its_gradient(integrator):
    """With no stiffness of its own the repulsion's is the springs' median (the mean of
    the two middle ones of eight distinct values), and the impulse is the spring's bound
    (with the linearised step, also the solve's penalty springs' stiffness): the
    stiffness gradient includes the median's share (to those two springs), checked
    against differences; without it, it would not match."""
    run = dict(STRADDLING_RUN, integrator=integrator, **SOLVED.get(integrator, {}))
    model = straddling(0.05, k_r=None)
    value, grads = ms.gradient(model, objective, "stiffness", **run)
    values = model_values(model)
    direction = np.random.default_rng(3).normal(size=8)
    direction /= np.abs(direction).max()
    numeric = richardson_difference(lambda **c: straddling(0.05, k_r=None, **c), values, "stiffness", direction, run,
                                    1e-4 * values["stiffness"].max())
    exact = float(np.sum(grads["stiffness"] * direction))
    assert abs(exact - numeric) <= 1e-6 * abs(numeric), (exact, numeric)
    middle = np.argsort(values["stiffness"])[3:5]
    shares = np.zeros(8)
    shares[middle] = 1.0
    _, fixed = ms.gradient(straddling(0.05, k_r=float(np.median(values["stiffness"]))), objective, "stiffness", **run)
    np.testing.assert_allclose(grads["stiffness"] - fixed["stiffness"], shares * (grads["stiffness"] -
                               fixed["stiffness"])[middle].mean(), rtol=1e-9, atol=1e-15)
    assert abs((grads["stiffness"] - fixed["stiffness"])[middle[0]]) > 1e-3 * np.abs(fixed["stiffness"]).max()



@pytest.mark.parametrize("returned, words", [
    (1.0, ["(value, partials) pair"]),
    ((float("nan"), {}), ["not a finite number"]),
    (("x", {}), ["must be a number"]),
    ((1.0, []), ["partials must be a dict"]),
    ((1.0, {"forces": 0}), ["unknown partials key 'forces'"]),
    ((1.0, {"positions": np.zeros((1, 16, 3))}), ["partials['positions'] has shape (1, 16, 3)", "(3, 16, 3)"]),
    ((1.0, {"velocities": np.full((3, 16, 3), np.inf)}), ["partials['velocities']", "not finite"]),
    # issue 60: these failed without the "objective:" prefix, gave inf, or were cut to their real part
    ((1.0, {"positions": "abc"}), ["partials['positions']", "not numbers"]),
    ((1.0, {"positions": np.full((3, 16, 3), 1 + 1j)}), ["partials['positions']", "complex"]),
    ((1.0, {"positions": np.full((3, 16, 3), 1e308)}), ["overflow", "1e+308"]),
])
def test_a_bad_objective_result_names_the_objective(returned, words):
    with pytest.raises(ValueError) as info:
        ms.gradient(sheet(), lambda frames: returned, "stiffness", steps=2, dt=1e-3, integrator="symplectic")
    assert str(info.value).startswith("objective: ")
    for word in words:
        assert word in str(info.value), (word, str(info.value))


@pytest.mark.parametrize("integrator, options", [
    pytest.param("implicit", dict(preconditioner="multigrid", loops="parallel"), id="implicit-multigrid", marks=FULL),
    pytest.param("implicit", dict(preconditioner="none", definiteness_fix=False), id="implicit-no-fix", marks=FULL),
    pytest.param("implicit", dict(preconditioner="none"), id="implicit-none", marks=FULL),
    pytest.param("backward-euler", dict(preconditioner="multigrid"), id="backward-euler-multigrid", marks=FULL),
    pytest.param("midpoint", dict(preconditioner="block-jacobi"), id="midpoint-block-jacobi", marks=FULL)])
def test_solved_gradients_at_a_frame_step(integrator, options):
    """Steps of dt = 1/60 s (compressed springs clamped by the definiteness fix, or not),
    the adjoint solved with the run's own preconditioner: directional derivatives in every
    parameter against central differences (``directional_difference``) to 1e-6 relative.
    Six steps: from the eighth on, the damped sheet's Newton iterations stall near 2e-9
    of the first residual (the line search's incremental potential and the residual
    part ways by the damping's turning, which Newton's operator leaves out), so tighter
    tolerances run the 200 iterations allowed and only the time grows."""
    model = sheet()
    run = run_of(integrator, **dict(options, dt=1 / 60, steps=6))
    value, grads = ms.gradient(model, objective, list(PARAMETERS), **run)
    values = model_values(model)
    rng = np.random.default_rng(11)
    for name in PARAMETERS:
        direction = unit_direction(rng, values, name)
        numeric = directional_difference(sheet, values, name, direction, integrator, run)
        exact = float(np.sum(grads[name] * direction))
        assert abs(exact - numeric) <= 1e-6 * abs(numeric), (name, exact, numeric)


@pytest.mark.parametrize("reason, advice", [("max_iter", "larger cg_max_iter"),
                                             ("stalled", "linearised 'implicit' integrator")])
def test_a_gradient_error_says_what_to_change(reason, advice):
    """A solve that ran out of iterations can be given more; one that stalled (round-off,
    or MINRES on a nearly singular Jacobian of a Newton-solved step) cannot: its advice
    is another tolerance, dt or integrator."""
    error = GradientError(8, reason, 0.11, "backward-euler")
    assert "step 9" in str(error) and advice in str(error), str(error)


def test_an_adjoint_solve_that_stops_short_is_an_error():
    """CG limited to 2 iterations: the forward steps go on unconverged (as a Simulation's
    do, counted in cg_failures), the first adjoint solve that stops short raises
    GradientError naming the step and the reason; no gradient is returned."""
    from massspring.support.errors import GradientError

    with pytest.raises(GradientError, match=r"implicit gradient: the adjoint solve of step 10 stopped \(max_iter"):
        ms.gradient(sheet(), objective, "stiffness", **run_of("implicit", cg_max_iter=2, preconditioner="none"))


THREADS_SCRIPT = """
import hashlib, sys
import numpy as np
import massspring as ms
model = ms.load_scene("cloth").with_params(resolution=12).model()
def last(frames):
    partial = np.zeros_like(frames.positions)
    partial[-1] = 1.0
    return float(frames.positions[-1].sum()), {"positions": partial, "velocities": frames.velocities}
for integrator, options in (("symplectic", {"dt": 1e-3}), ("rk4", {"dt": 1e-3}),
                            ("implicit", {"dt": 1e-3, "preconditioner": "multigrid"}),
                            ("backward-euler", {"dt": 1 / 60, "preconditioner": "multigrid"})):
    value, grads = ms.gradient(model, last, ["stiffness", "damping", "masses", "positions", "velocities"],
                               steps=6, every=2, integrator=integrator, loops="parallel", checkpoint=4, **options)
    digest = hashlib.sha256(np.float64(value).tobytes())
    for name in sorted(grads):
        digest.update(grads[name].tobytes())
    print(integrator, digest.hexdigest())
sheets = ms.load_scene("sheets").with_params(resolution=6).model()
value, grads = ms.gradient(sheets, last, ["stiffness", "masses", "positions"], steps=30, every=3,
                           integrator="implicit", dt=1 / 60, loops="parallel", checkpoint=8)
digest = hashlib.sha256(np.float64(value).tobytes())
for name in sorted(grads):
    digest.update(grads[name].tobytes())
print("sheets-implicit", digest.hexdigest())
shaken = model.replaced(strain_limit=1e-3, velocities=np.random.default_rng(0).normal(0.0, 0.5, (model.n_particles, 3)))
value, grads = ms.gradient(shaken, last, ["rest_lengths", "masses", "positions"], steps=6, every=2,
                           integrator="implicit", dt=1e-3, loops="parallel", checkpoint=4)
digest = hashlib.sha256(np.float64(value).tobytes())
for name in sorted(grads):
    digest.update(grads[name].tobytes())
print("strain-limit", digest.hexdigest())
"""


@FULL
def test_gradients_do_not_depend_on_the_thread_count(tmp_path):
    """Parallel adjoint kernels write each item from one thread and gather springs in a
    fixed order (no atomics), and the adjoint solve's sums are fixed-block sums (MINRES's,
    of a Newton-solved step, numpy's pairwise sums): 1 and 2 threads give the same bits for
    the symplectic, RK4, multigrid implicit and backward-Euler gradients (the last at dt
    1/60 s, where compressed springs make its adjoint MINRES's); and the implicit
    gradient through the sheets scene's self-collision (the upper sheet landing: the
    pass acting, pairs in the solve), whose pairs the backward pass takes in the order
    of their particles, not the threads' order; and the implicit gradient through a strain
    limit (its iterations' adjoint gathers each particle's springs in order)."""
    import os
    import subprocess
    import sys

    out = []
    for threads in ("1", "2"):
        env = dict(os.environ, TI_CPU_MAX_NUM_THREADS=threads)
        proc = subprocess.run([sys.executable, "-c", THREADS_SCRIPT], capture_output=True, text=True, env=env,
                              cwd=tmp_path, timeout=600)
        assert proc.returncode == 0, proc.stderr
        out.append([line for line in proc.stdout.splitlines()
                    if line.split()[0] in ("symplectic", "rk4", "implicit", "backward-euler", "sheets-implicit",
                                           "strain-limit")])
    assert len(out[0]) == 6 and out[0] == out[1], out


@pytest.mark.full
def test_a_pass_whose_scales_lift_its_rounding_is_replayed():
    """The sheets scene at 12 x 12 with BDF2, 120 steps: in step 114 the pass pushes two
    particles hit by 17 pairs each and then scales them to 0.82 of a displacement only
    2e-5 m past their bound, which lifts the push's fixed-point rounding (1e-12 m) to
    4e-11 m in their positions; the replay rounds as the pass does and matches it (an
    exact replay missed it by 3.9e-11 m, above its check, and the gradient was refused)."""
    scene = ms.load_scene("sheets").with_params(resolution=12)

    def height(frames):
        partial = np.zeros_like(frames.positions)
        partial[-1, :, 2] = 1.0
        return float(frames.positions[-1, :, 2].sum()), {"positions": partial}

    value, grads = ms.gradient(scene.model(), height, "stiffness", steps=120, every=120, integrator="bdf2",
                               dt=scene.dt["bdf2"])
    assert np.isfinite(value) and np.all(np.isfinite(grads["stiffness"])) and np.abs(grads["stiffness"]).max() > 0


@FULL
def test_a_gradient_from_springs_at_rest_warns_of_the_kink():
    """The cloth scene's start state has every spring at its rest length, where the
    definiteness fix's clamp has a kink (issue 60: the implicit gradient -0.1625 against
    one-sided differences -0.0947 and -0.1478, silently): ``KinkWarning`` names the
    springs; none without the fix, off the rest lengths, or for an integrator without it."""
    import warnings

    model = ms.load_scene("cloth").with_params(resolution=4).model()

    def last_z(frames):
        partials = np.zeros_like(frames.positions)
        partials[-1, :, 2] = 1.0
        return float(frames.positions[-1, :, 2].sum()), {"positions": partials}

    with pytest.warns(ms.KinkWarning, match=r"^gradient: 58 of 58 springs start at their rest length"):
        ms.gradient(model, last_z, "damping", steps=3, integrator="implicit", dt=1e-2)
    moved = model.replaced(positions=model.positions * 1.001)
    with warnings.catch_warnings():
        warnings.simplefilter("error", ms.KinkWarning)
        ms.gradient(model, last_z, "damping", steps=3, integrator="implicit", dt=1e-2, definiteness_fix=False)
        ms.gradient(moved, last_z, "damping", steps=3, integrator="implicit", dt=1e-2)
        ms.gradient(model, last_z, "damping", steps=3, integrator="symplectic", dt=1e-3)

