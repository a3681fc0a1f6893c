"""Strain limiting (``Model(strain_limit=...)``, ``massspring/passes/strain_limit/``): no spring
stretched past the limit after any step of any integrator, momentum kept, nothing of it
in a run without one, bad values refused by name."""

import numpy as np
import pytest

import massspring as ms
from conftest import FULL
from massspring.scene import generators
from massspring.gradients import differentiable
from massspring.integrators import INTEGRATORS, taken
from massspring.scene import SceneError, builtin_scenes, load_scene

LIMIT = 0.1
ROUND_OFF = 1e-12  # numpy's l / l0 - 1 from the positions read back against the kernel's


def stretch(model, x):
    """The largest l / l0 - 1 of the model's springs at positions x."""
    e = model.springs
    return float((np.linalg.norm(x[e[:, 1]] - x[e[:, 0]], axis=1) / model.rest_lengths - 1).max())


def hanging(strain_limit=None, **kw):
    """A soft 6 x 6 cloth pinned at two corners, falling: its springs stretch past 30%
    within 0.2 s without a limit."""
    args = generators.grid(resolution=6, size=0.5, mass=0.5, stiffness=30.0, damping=0.5, shear=1.0, bend=0.0,
                           pin="corners", gravity=[0.0, 0.0, -9.81])
    return ms.Model(**args, strain_limit=strain_limit, **kw)


DT = {"explicit": 2e-4, "symplectic": 2e-4, "rk4": 2e-4}


@pytest.mark.fast_sample(integrator=["symplectic", "implicit"])
@pytest.mark.parametrize("integrator", sorted(INTEGRATORS))
def test_no_spring_ends_a_step_past_the_limit(integrator):
    """Every step of 0.2 s ends with every spring within the limit (+ the pass's tolerance),
    where the same run without a limit stretches springs past 3 times the limit."""
    dt = DT.get(integrator, 1e-2)
    steps = round(0.2 / dt)
    free = ms.Simulation(hanging(), integrator, dt=dt)
    free.step(steps)
    assert stretch(free.model, free.positions) > 3 * LIMIT
    sim = ms.Simulation(hanging(LIMIT), integrator, dt=dt)
    passes = 0
    for _ in range(steps):
        sim.step()
        assert stretch(sim.model, sim.positions) <= LIMIT + ROUND_OFF
        stats = sim.strain_limit_stats
        passes += stats["before"] > LIMIT
        assert stats["unmet"] == 0 and stats["after"] <= LIMIT
    assert passes > steps // 10  # the limit did the work
    pins = sim.model.fixed
    np.testing.assert_array_equal(sim.positions[pins], sim.model.positions[pins])  # pins never move
    assert np.all(np.isfinite(sim.velocities))


@pytest.mark.parametrize("integrator", ["symplectic", "implicit"])
def test_serial_and_parallel_loops_limit_alike(integrator):
    """All iterations in one serial launch (small systems) or one parallel launch each:
    the same iterations and, for the symplectic steps, the same bits."""
    dt = DT.get(integrator, 1e-2)
    runs = []
    for loops in ("serial", "parallel"):
        sim = ms.Simulation(hanging(LIMIT), integrator, dt=dt, loops=loops)
        sim.step(round(0.15 / dt))
        runs.append((sim.positions, sim.strain_limit_stats))
    assert runs[0][1]["steps"] > 0 and runs[0][1]["most"] == runs[1][1]["most"]
    if integrator == "symplectic":
        np.testing.assert_array_equal(runs[0][0], runs[1][0])
    else:  # the serial and parallel CG sum in other orders
        np.testing.assert_allclose(runs[0][0], runs[1][0], rtol=0, atol=1e-12)  # measured 2e-16


@pytest.mark.fast_sample(integrator=["symplectic", "implicit"])
@pytest.mark.parametrize("integrator", ["symplectic", "implicit"])
def test_the_limit_keeps_linear_momentum(integrator):
    """A free cloth (no pins, gravity or colliders) flung apart: the pass moves both ends of
    a spring by shares of one correction, so total momentum stays what it was to
    round-off while the limit acts."""
    args = generators.grid(resolution=5, size=0.4, mass=0.3, stiffness=20.0, damping=0.0, shear=1.0, bend=0.0,
                           pin="none", gravity=[0.0, 0.0, 0.0])
    rng = np.random.default_rng(7)
    args["velocities"] = rng.normal(0.0, 1.0, (len(args["positions"]), 3))
    masses = np.full(len(args["positions"]), 0.3 / len(args["positions"]))
    model = ms.Model(**args, strain_limit=LIMIT)
    start = masses @ model.velocities
    sim = ms.Simulation(model, integrator, dt=5e-3, **taken(integrator, {"cg_tol": 1e-14}))
    acted = 0
    for _ in range(20):
        sim.step()
        acted += sim.strain_limit_stats["before"] > LIMIT
        np.testing.assert_allclose(masses @ sim.velocities, start, rtol=0, atol=1e-12 * np.abs(masses @ np.abs(
            sim.velocities)).max())
    assert acted >= 5


def test_the_limit_keeps_a_draped_cloth_on_its_collider():
    """A cloth dropped on a sphere with the implicit step: springs within the limit and no
    particle left inside the sphere (a particle the pass moves into it is put back)."""
    scene = load_scene("drape").with_params(resolution=12, strain_limit=LIMIT)
    sim = scene.simulation()
    sphere = next(c for c in sim.model.colliders if type(c).__name__ == "Sphere")
    for _ in range(40):
        sim.step()
        assert stretch(sim.model, sim.positions) <= LIMIT + ROUND_OFF
        depth = sphere.radius - np.linalg.norm(sim.positions - np.asarray(sphere.center), axis=1)
        assert depth.max() <= 1e-9


def test_a_run_without_a_limit_has_nothing_of_it():
    model = hanging()
    sim = ms.Simulation(model, "implicit", dt=1e-2)
    assert sim.strain_limit_stats is None
    assert not {"sl_dx", "sl_k"} & set(sim._layout_names)
    limited = ms.Simulation(hanging(LIMIT), "implicit", dt=1e-2)
    assert {"sl_dx", "sl_k"} <= set(limited._layout_names)
    assert model.fingerprint() != hanging(LIMIT).fingerprint()


@pytest.mark.parametrize("value", [0, -0.1, float("nan"), float("inf"), True, "0.1", [0.1]])
def test_bad_limits_are_refused_by_name(value):
    with pytest.raises(ValueError, match="strain_limit: "):
        hanging(value)


def test_a_model_without_springs_cannot_have_a_limit():
    with pytest.raises(ValueError, match="strain_limit: the model has no springs"):
        ms.Model([[0.0, 0.0, 0.0]], np.zeros((0, 2), dtype=int), strain_limit=LIMIT)


def test_scene_key(tmp_path):
    scene = load_scene("drape").with_params(resolution=8, strain_limit=0.05)
    assert scene.model().strain_limit == 0.05
    assert load_scene("cloth").model().strain_limit is None  # 0: none
    path = tmp_path / "bad.toml"
    path.write_text(builtin_scenes()["chain"].read_text().replace("[model]", "[model]\nstrain_limit = -1", 1))
    with pytest.raises(SceneError, match=r"model.strain_limit: must be >= 0"):
        load_scene(path)


def test_run_prints_what_the_limit_did(capsys):
    from massspring.cli import main

    assert main(["run", "drape", "--set", "resolution=8", "--steps", "30", "--quiet"]) == 0
    line = next(line for line in capsys.readouterr().out.splitlines() if line.startswith("strain"))
    assert line.startswith("strain      limit 0.1: ") and "step(s) shortened springs" in line
    assert main(["run", "drape", "--set", "resolution=8", "--set", "strain_limit=0", "--steps", "3", "--quiet"]) == 0
    assert "strain " not in capsys.readouterr().out


def test_info_says_the_limit(capsys):
    from massspring.cli import main

    assert main(["info", "drape", "--set", "resolution=8"]) == 0
    assert "strain      limit 0.1: no spring longer than 1.1 times its rest length" in capsys.readouterr().out
    assert main(["info", "cloth", "--set", "resolution=8"]) == 0
    assert "strain " not in capsys.readouterr().out


@pytest.mark.parametrize("loops", ["serial", "parallel"])
def test_a_limit_the_pins_cannot_meet_never_makes_a_spring_worse(loops):
    """Issue 60: a 5-particle chain pinned 1.5 times its rest length apart cannot meet a
    limit of 0.1; the pass's 500 Jacobi iterations left its worst spring at 0.633 where
    the step had left it at 0.55. Now a pass that ends worse than it began is undone
    (the state the step left, bit for bit) and counted as undone; the summary says so."""
    n = 5
    x = np.column_stack([np.linspace(0, 1.5 * 0.4, n), np.zeros(n), np.zeros(n)])
    springs = np.column_stack([np.arange(n - 1), np.arange(1, n)])
    pinned = dict(masses=0.1, stiffness=100.0, rest_lengths=0.1, fixed=[0, n - 1], gravity=(0, 0, -9.81))
    limited = ms.Simulation(ms.Model(x, springs, strain_limit=0.1, **pinned), "implicit", dt=1 / 60, loops=loops)
    free = ms.Simulation(ms.Model(x, springs, **pinned), "implicit", dt=1 / 60, loops=loops)
    try:
        for step in range(1, 6):
            limited.step(1)
            free.step(1)
            stats = limited.strain_limit_stats
            assert stats["after"] <= stats["before"], stats
            assert stats["unmet"] == stats["undone"] == step
            assert np.array_equal(limited.positions, free.positions)  # each pass undone: the steps alone
    finally:
        limited.close()
        free.close()


@FULL
@pytest.mark.parametrize("integrator", ["bdf2", "midpoint"])
def test_pins_pulling_past_the_limit_do_not_pump_energy(integrator):
    """Issue 60: the chain above with its pins pulling apart at 1 m/s (0.5 m/s each):
    BDF2 and the midpoint rule stopped with a DivergenceError (steps 191 and 112; here
    147 and 144). The energy was the pins' work, not the integrators' (238 J in the
    springs after 250 steps of dt 1/60, as backward Euler's run has, measured), which the
    divergence check's bound left out (``simulation.pin_work``). Every pass would leave
    the worst spring worse and is undone, so the 250 steps (to strain 10) are the steps
    alone, bit for bit, and finish."""
    n = 5
    x = np.column_stack([np.linspace(0, 1.5 * 0.4, n), np.zeros(n), np.zeros(n)])
    springs = np.column_stack([np.arange(n - 1), np.arange(1, n)])
    pinned = dict(masses=0.1, stiffness=100.0, damping=0.5, rest_lengths=0.1, fixed=[0, n - 1],
                  gravity=(0, 0, -9.81), pin_velocity=[[-0.5, 0, 0], [0.5, 0, 0]])
    limited = ms.Simulation(ms.Model(x, springs, strain_limit=0.1, **pinned), integrator, dt=1 / 60)
    free = ms.Simulation(ms.Model(x, springs, **pinned), integrator, dt=1 / 60)
    try:
        limited.step(250)
        free.step(250)
        stats = limited.strain_limit_stats
        assert stats["before"] > 10 and stats["undone"] == stats["unmet"] == 250
        assert np.array_equal(limited.positions, free.positions)
        energy = limited.energy()
        assert energy["kinetic"] == free.energy()["kinetic"] < 1.0 and energy["spring"] > 200.0
    finally:
        limited.close()
        free.close()


# Gradients through the limit (issue 60): the pass's adjoint with its active set frozen
# (``massspring/passes/strain_limit/backward.py``), against central differences of plain runs
GRADIENT_LIMIT = 0.02
GRADIENT_RUN = dict(steps=12, every=3, dt=4e-3)
NEWTON_SOLVED = dict(cg_tol=1e-13, newton_tol=1e-12, newton_max_iter=200)
SOLVED = {"implicit": dict(cg_tol=1e-13), "backward-euler": NEWTON_SOLVED, "bdf2": NEWTON_SOLVED,
          "midpoint": NEWTON_SOLVED}


def shaken(colliders=(), seed=3, **changes):
    """A 4 x 4 cloth hanging from one corner, jittered, with random masses, rest lengths
    and velocities and a limit of 2%: its springs pass the limit in most steps, and the
    pass meets it."""
    args = generators.grid(resolution=4, size=0.3, mass=0.2, stiffness=30.0, damping=0.2, shear=1.0, bend=0.0,
                           pin="corners", gravity=[0.0, 0.0, -9.81])
    rng = np.random.default_rng(seed)
    n, m = len(args["positions"]), len(args["springs"])
    args["fixed"] = args["fixed"][:1]
    values = dict(positions=args["positions"] + rng.normal(0.0, 0.002, (n, 3)), masses=rng.uniform(0.01, 0.02, n),
                  rest_lengths=rng.uniform(0.98, 1.0, m) * ms.Model(**args).rest_lengths,
                  velocities=rng.normal(0.0, 0.3, (n, 3)))
    values.update(changes)
    return ms.Model(**dict(args, **values), strain_limit=GRADIENT_LIMIT, colliders=list(colliders))


def weighted(frames):
    """L = sum C . X + |V|^2 / 2 over the frames."""
    c = np.random.default_rng(11).normal(size=frames.positions.shape)
    value = np.sum(c * frames.positions) + 0.5 * np.sum(frames.velocities ** 2)
    return value, {"positions": c, "velocities": frames.velocities}


def plain_value(model, integrator, sizes=None):
    """``weighted`` of the run ``ms.gradient`` takes (``GRADIENT_RUN``, or steps of
    ``sizes`` with frames every 3), as plain steps; and the steps the limit moved
    particles in."""
    at = np.arange(0, GRADIENT_RUN["steps"] + 1, GRADIENT_RUN["every"])
    dt = GRADIENT_RUN["dt"] if sizes is None else float(sizes[0])
    sim = ms.Simulation(model, integrator, dt=dt, **SOLVED.get(integrator, {}))
    positions, velocities = [], []
    try:
        if sizes is not None:
            sim.replay(sizes[:0])
        for k in at:
            if sizes is None:
                sim.step(k - sim.steps)
            else:
                sim.replay(sizes[sim.steps:k])
            positions.append(sim.positions)
            velocities.append(sim.velocities)
        acted = sim.strain_limit_stats["steps"]
    finally:
        sim.close()
    frames = ms.Frames(np.array(positions), np.array(velocities), None, at)
    return weighted(frames)[0], acted


WRT = ("positions", "velocities", "rest_lengths", "masses", "stiffness")
# Central differences' step, relative to the largest value: 1e-6 crossed a switch of the
# pass's active set (the implicit run's positions: -857.6 against -490.97 at 1e-7, 1e-8 and
# 1e-9); the stiffness, whose effect the limit mostly takes away (its derivative 1e4 times
# smaller), 1e-5. The noise of a run's value, relative to it, that a difference divides by
# the step: round-off through the run (measured: 2e-15 of symplectic Euler's, its
# velocities' derivative 1e-6 off at a step of 9e-8 and 5e-10 at 9e-6; 2e-14 of RK4's), and
# for the implicit and Newton-solved steps their equations met to about 1e-13 (backward
# Euler's stiffness derivative 2e-8 off at a step of 3e-5)
DIFFERENCE_STEP = {"stiffness": 1e-5}
NOISE = {"implicit": 1e-12, "backward-euler": 1e-12, "bdf2": 1e-12, "midpoint": 1e-12}
ROUND_OFF_NOISE = 1e-13


def check_against_differences(make, integrator, acted_at_least=GRADIENT_RUN["steps"] // 2, sizes=None):
    """Directional derivatives of ``weighted`` in each of ``WRT`` (random directions)
    against central differences of plain runs: within 1e-6 relative, or the noise that
    the difference's step lifts the run's value's to."""
    model = make()
    run = GRADIENT_RUN if sizes is None else dict(dts=sizes, every=list(range(3, len(sizes) + 1, 3)))
    value, grads = ms.gradient(model, weighted, list(WRT), integrator=integrator, checkpoint=5, **run,
                               **SOLVED.get(integrator, {}))
    plain, acted = plain_value(model, integrator, sizes)
    assert acted >= acted_at_least  # the limit acted
    assert value == pytest.approx(plain, rel=1e-12)
    rng = np.random.default_rng(5)
    for name in WRT:
        base = getattr(model, name)
        direction = rng.normal(size=base.shape)
        if name in ("positions", "velocities"):
            direction[model.fixed] = 0.0
        eps = DIFFERENCE_STEP.get(name, 1e-7) * np.abs(base).max()
        ends = [plain_value(make(**{name: base + sign * eps * direction}), integrator, sizes)[0]
                for sign in (1, -1)]
        difference = (ends[0] - ends[1]) / (2 * eps)
        derivative = float(np.sum(grads[name] * direction))
        noise = NOISE.get(integrator, ROUND_OFF_NOISE) * abs(value) / eps
        assert derivative == pytest.approx(difference, rel=1e-6, abs=noise), name


@pytest.mark.fast_sample(integrator=["symplectic"])
@pytest.mark.parametrize("integrator", sorted(differentiable()))
def test_gradients_through_the_limit_match_central_differences(integrator):
    check_against_differences(shaken, integrator)


def draped(seed=3, **changes):
    """The 4 x 4 cloth of ``shaken``, free, laid on a ball of radius 0.15 m (0.1 mm above
    it), its springs 2-4% shorter than the chords between their ends: the pass shortens
    chords of the ball, moving their ends into it, and ``project`` puts them back."""
    args = generators.grid(resolution=4, size=0.3, mass=0.2, stiffness=30.0, damping=0.2, shear=1.0, bend=0.0,
                           pin="none", gravity=[0.0, 0.0, -9.81])
    rng = np.random.default_rng(seed)
    radius, centre = 0.15, np.array([0.15, 0.15, -0.15])
    flat = np.asarray(args["positions"]) - centre
    on_ball = centre + radius * (1 + 1e-3) * flat / np.linalg.norm(flat, axis=1)[:, None]
    ends = np.asarray(args["springs"])
    chords = np.linalg.norm(on_ball[ends[:, 1]] - on_ball[ends[:, 0]], axis=1)
    n, m = len(on_ball), len(ends)
    values = dict(positions=on_ball, masses=rng.uniform(0.01, 0.02, n), rest_lengths=rng.uniform(0.96, 0.98, m) * chords,
                  velocities=rng.normal(0.0, 0.05, (n, 3)))
    values.update(changes)
    ball = ms.Sphere(center=centre, radius=radius)
    return ms.Model(**dict(args, **values), strain_limit=GRADIENT_LIMIT, colliders=[ball])


@FULL
@pytest.mark.parametrize("integrator", ["symplectic", "implicit"])
def test_gradients_through_the_limit_on_a_collider(integrator):
    """The pass moving particles into a ball and putting them back (``project``'s Jacobian
    in ``strain_limit_adjoint``: without it, this test fails)."""
    check_against_differences(draped, integrator, acted_at_least=2)


@FULL
@pytest.mark.parametrize("integrator", ["symplectic", "bdf2"])
def test_gradients_through_the_limit_with_steps_of_varying_size(integrator):
    """Twelve steps of 2 to 6 ms in no order (``dts``): each step's pass runs backwards
    with its own size (BDF2 with its variable-step coefficients)."""
    sizes = np.random.default_rng(2).uniform(2e-3, 6e-3, GRADIENT_RUN["steps"])
    check_against_differences(shaken, integrator, sizes=sizes)


def test_a_gradients_memory_check_counts_the_limits_records():
    """``gradients.host_bytes`` (the memory check before a gradient runs) adds the limit's
    records of a stretch and one step's iterations (``backward.host_bytes``)."""
    from massspring.gradients import host_bytes
    from massspring.passes.strain_limit import ITERATIONS
    from massspring.passes.strain_limit.backward import host_bytes as pass_bytes

    limited = shaken()
    free = limited.replaced(strain_limit=None)
    n = limited.n_particles
    assert pass_bytes(n, 40) == n * (48 * 40 + 24 * (ITERATIONS + 2))
    assert host_bytes(limited, "implicit", 100, 5, 40) - host_bytes(free, "implicit", 100, 5, 40) == pass_bytes(n, 40)
