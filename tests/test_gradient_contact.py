"""Gradients through contact (``massspring.gradient`` with colliders): every integrator's
contact response, friction sliding and sticking, restitution and curved colliders,
against central differences of the forward runs (helpers from ``test_gradient``). Apart
from ``test_gradient.py`` so that the full suite's two workers share the gradient
tests more evenly (``--dist loadfile`` gives each file to one worker)."""

import dataclasses

import numpy as np
import pytest

import massspring as ms
from test_gradient import (SOLVED, STILL_AIR, directional_difference, model_values, objective, run_value, sheet_grid,
                           sheet_values)

# conftest: as test_gradient's (each test compiles the adjoints of its own configuration)
RESET_BETWEEN_TESTS = 1.0e9


def ground_sheet(case, **changes):
    """A 3 x 3 damped sheet with shear springs on the ground plane z = 0 (friction,
    restitution): "slide" lies on it sliding, "stick" lies on it with friction enough to
    hold every particle, "fall" starts 3-4 cm above it, lands in the run and slides."""
    rng = np.random.default_rng(2)
    positions, springs = sheet_grid()
    n, m = len(positions), len(springs)
    friction, restitution = {"slide": (0.3, 0.0), "stick": (1.0, 0.0), "fall": (0.2, 0.5)}[case]
    if case == "fall":
        velocities = np.tile([0.5, 0.0, -1.0], (n, 1)) + rng.normal(0, 0.05, (n, 3))
        positions[:, 2] = 0.031 + rng.uniform(0, 0.01, n)
    else:
        velocities = (np.tile([1.0, 0.3, 0.0], (n, 1)) if case == "slide" else 0) + rng.normal(0, 0.01, (n, 3))
        velocities[:, 2] = 0
    values = sheet_values(rng, positions, velocities, m)
    values.update(changes)
    plane = ms.Plane((0, 0, 0), (0, 0, 1), friction=friction, restitution=restitution)
    return ms.Model(values.pop("positions"), springs, colliders=[plane], **values)


@pytest.mark.fast_sample(integrator=["symplectic"], case=["slide"])
@pytest.mark.parametrize("integrator", ["explicit", "symplectic", "rk4"])
@pytest.mark.parametrize("case", ["slide", "stick", "fall"])
def test_contact_with_a_plane_has_the_gradient_of_its_branches(integrator, case):
    """Resting contact on a plane, sliding or sticking, and a landing with restitution:
    the contact response's branches do not switch under a small change, so the gradient
    (``contact.respond_adjoint``, branches frozen) agrees with central differences to
    1e-6 relative. A sticking sheet does not move along the plane: its value hardly
    depends on the springs, so there only the initial state's gradients are compared
    (the others are at the differences' round-off)."""
    names = ["positions", "velocities"] if case == "stick" else STILL_AIR
    run = dict(steps=30, every=5, dt=2e-3, integrator=integrator, checkpoint=7)
    check_against_differences(lambda **changes: ground_sheet(case, **changes), names, run, along_plane=case != "fall")


ROUNDING = 2e-15  # a run's objective varies by this much of itself between neighbouring parameters (measured 1.3e-15)


def check_against_differences(make, names, run, along_plane=False):
    """The gradient of ``make()``'s run against central differences of the runs of
    ``make(name=value +- eps direction)``, to 1e-6 relative, along a random direction per
    name; ``along_plane``: the initial state's directions have no z (particles lying on
    z = 0, which a lift would take off). The step is 1e-5 of the largest value, or larger
    where the derivative is so small against the objective that the runs' round-off
    (``ROUNDING`` of the value, over the step) would reach a tenth of the tolerance: the
    sphere-stick sheet's damping derivative is 5e-5 of its value, and at 1e-5 its
    difference was off by 8e-8 or 1.06e-6 of it as round-off fell (measured at steps 1e-6
    to 1e-3: -9.2e-6, -1.06e-6, -1.5e-8, +1.5e-10; a scan of 21 runs put the round-off at
    2.6e-14 of a value of 55)."""
    model = make()
    value, grads = ms.gradient(model, objective, names, **run)
    values = model_values(model)
    rng = np.random.default_rng(3)
    for name in names:
        direction = rng.normal(size=np.shape(values[name]))
        if name in ("positions", "velocities") and along_plane:
            direction[:, 2] = 0
        direction /= np.abs(direction).max()
        exact = float(np.sum(grads[name] * direction))
        noise = ROUNDING * max(abs(value), 1.0) / (0.1 * 1e-6 * max(abs(exact), 1e-300))
        eps = max(1e-5 * max(1.0, np.abs(values[name]).max()), noise)
        ends = [run_value(make(**{name: values[name] + sign * eps * direction}), objective, run) for sign in (1, -1)]
        numeric = (ends[0] - ends[1]) / (2 * eps)
        assert abs(exact - numeric) <= 1e-6 * abs(numeric), (name, exact, numeric, eps)


def curved_sheet(collider, **changes):
    """The 3 x 3 damped sheet with shear springs falling 3-4 cm onto a curved surface with
    restitution 0.5: "sphere" (radius 0.5 m, its top under the sheet's middle) or "box"
    (a rounded edge of radius 0.2 m along y under it), friction 0.2 (sliding as it lands),
    "sphere-stick" with friction 3 (sticking where it lands), or "groove": two planes
    (friction 0.1, no restitution) tilted by 0.5 towards a valley along y under the
    sheet's middle row, which lands in the valley and then meets both within a step
    (the response takes them in turn: the second moves it on from the first's landing
    and projects it out of the first again)."""
    rng = np.random.default_rng(5)
    positions, springs = sheet_grid()
    n, m = len(positions), len(springs)
    if collider.startswith("sphere"):
        colliders = [ms.Sphere((0.1, 0.1, -0.5), 0.5, friction=3.0 if collider == "sphere-stick" else 0.2,
                               restitution=0.5)]
        height = np.sqrt(0.25 - (positions[:, 0] - 0.1) ** 2 - (positions[:, 1] - 0.1) ** 2) - 0.5
    elif collider == "box":  # the box's top at z = 0, its rounded edge (x = 0.15) under the sheet
        colliders = [ms.Box((-1.0, -1.0, -1.0), (0.15, 1.0, 0.0), radius=0.2, friction=0.2, restitution=0.5)]
        over = np.maximum(positions[:, 0] - (0.15 - 0.2), 0.0)
        height = np.sqrt(np.maximum(0.04 - over ** 2, 0.0)) - 0.2
    elif collider == "edges":  # two overlapping boxes' rounded edges (radius 0.2) meeting at x = 0.1, 90 degrees
        colliders = [ms.Box((-1.0, -1.0, -1.0), (0.16, 1.0, 0.0), radius=0.2, friction=0.1),
                     ms.Box((0.04, -1.0, -1.0), (1.0, 1.0, 0.0), radius=0.2, friction=0.1)]
        over = np.where(positions[:, 0] < 0.1, positions[:, 0] + 0.04, 0.24 - positions[:, 0])
        height = np.sqrt(0.04 - over ** 2) - 0.2
    else:
        colliders = [ms.Plane((0.1, 0.0, 0.0), (side_x * 0.5, 0.0, 1.0), friction=0.1) for side_x in (-1.0, 1.0)]
        height = 0.5 * np.abs(positions[:, 0] - 0.1)
    positions[:, 2] = height + 0.031 + rng.uniform(0, 0.01, n)
    drift = 0.0 if collider in ("groove", "edges") else 0.5  # there the middle row lands in the valley
    velocities = np.tile([drift, 0.2, -1.0], (n, 1)) + rng.normal(0, 0.05, (n, 3))
    values = sheet_values(rng, positions, velocities, m)
    values.update(changes)
    return ms.Model(values.pop("positions"), springs, colliders=colliders, **values)


@pytest.mark.fast_sample(integrator=["symplectic"], collider=["sphere"])
@pytest.mark.parametrize("integrator", ["explicit", "symplectic", "rk4"])
@pytest.mark.parametrize("collider", ["sphere", "sphere-stick", "box", "groove"])
def test_contact_with_a_curved_surface_has_the_gradient_of_its_branches(integrator, collider):
    """A sheet landing on a sphere or on a box's rounded edge, sliding or sticking: the
    surface's normal turns with the position (``curvature``), in the impulse and in the
    projection onto the surface; with the branches frozen, the gradient agrees with
    central differences to 1e-6 relative in every parameter kind and the initial state."""
    run = dict(steps=60 if collider == "groove" else 30, every=5, dt=2e-3, integrator=integrator, checkpoint=7)
    check_against_differences(lambda **changes: curved_sheet(collider, **changes), STILL_AIR, run)


BACKWARD_EULER_CONTACT = dict(integrator="backward-euler", steps=30, every=5, dt=2e-3, checkpoint=7, cg_tol=1e-13,
                              newton_tol=1e-12, newton_max_iter=200)
# Backward Euler on every sheet; BDF2 and midpoint, whose steps share its contact and
# friction adjoint and differ in the step around it, on two each (a sticking and a
# sliding one, a plane and a curved or two-sided collider): the full suite's time.
NEWTON_CONTACT_CASES = [("backward-euler", case) for case in ("slide", "stick", "fall", "sphere", "sphere-stick", "box",
                                                              "groove")] + \
    [("bdf2", case) for case in ("stick", "box")] + [("midpoint", case) for case in ("slide", "groove")]


@pytest.mark.full  # the fast tier's Newton contact gradient: the definiteness fix's, below
@pytest.mark.parametrize("integrator_case", NEWTON_CONTACT_CASES, ids=["-".join(pair) for pair in NEWTON_CONTACT_CASES])
def test_contact_in_a_newton_solved_step_has_the_gradient_of_its_branches(integrator_case):
    """Backward Euler's, BDF2's and the midpoint rule's contact constraints and friction,
    the implicit step's adjoint pieces at Newton's converged iterate (the impulses there
    are the residual's constrained part, kept with the history; BDF2 and the midpoint
    rule take a backward-Euler step at a contact, BDF2 the next one too, as each step
    recorded): against central differences to 1e-6 relative as for the implicit step.
    Without the definiteness fix, so that Newton converges quadratically and the runs
    meet their equations to round-off: with it, Newton converges linearly where springs
    are compressed and differences of 1e-5 carry noise of 1e-6 to 3e-4 (the sphere's
    damping), falling with larger steps (the next test). Left out, their differences
    varying with the step: backward Euler in the groove of two rounded edges (damping: 4e-7
    to 7e-6, a friction branch near its switch), the midpoint rule on the sphere (damping:
    3.5e-6, 1.6e-6 and 9e-8 at steps of 3e-6, 1e-5 and 1e-4). Measured by changing a
    piece: BDF2's adjoint taking its base at every step but the first (fall: up to 0.23
    relative), the midpoint rule's adjoint taking its own step at a contact (fall: 1.1)."""
    integrator, case = integrator_case
    names = ["positions", "velocities"] if case == "stick" else STILL_AIR
    check_against_differences(lambda **changes: contact_case(case, **changes), names,
                              dict(BACKWARD_EULER_CONTACT, integrator=integrator, definiteness_fix=False),
                              along_plane=case in ("slide", "stick"))


def test_contact_in_a_backward_euler_step_with_the_definiteness_fix():
    """With the fix, the adjoint's system is the true Jacobian's, solved by MINRES
    preconditioned with the fixed operator's preconditioner on the constrained particles'
    free directions: a sheet
    landing on a box's rounded edge with friction, against Richardson's combination of
    central differences of 1e-3 and 2e-3 of each value (``directional_difference``), to
    1e-6 relative, in every parameter kind but the initial positions (a step that large
    moves landings to other steps)."""
    make = lambda **changes: contact_case("box", **changes)  # noqa: E731
    model = make()
    names = [name for name in STILL_AIR if name != "positions"]
    value, grads = ms.gradient(model, objective, names, **BACKWARD_EULER_CONTACT)
    values = model_values(model)
    rng = np.random.default_rng(3)
    for name in names:
        direction = rng.normal(size=np.shape(values[name]))
        direction /= np.abs(direction).max()
        numeric = directional_difference(make, values, name, direction, "backward-euler", BACKWARD_EULER_CONTACT)
        exact = float(np.sum(grads[name] * direction))
        assert abs(exact - numeric) <= 1e-6 * abs(numeric), (name, exact, numeric)


def test_newton_converges_in_every_step_of_the_landing_on_the_box():
    """The run the test above differentiates: every backward-Euler step meets newton_tol
    1e-12 within a few iterations. Before the Newton direction's prescribed directions were
    projected out, their round-off (eps |v| along the sliding particle's normal, which
    carries the contact impulse's share of the energy's gradient) made the line search see
    a rise where the step descends, cut it 12 times an iteration and stall at 1e-9 for
    200 iterations (steps 15 and 18 on one CPU), leaving a run whose objective moved by
    1e-10 between neighbouring parameters: the differences' noise."""
    run = {k: v for k, v in BACKWARD_EULER_CONTACT.items() if k not in ("steps", "every", "checkpoint", "integrator")}
    sim = ms.Simulation(contact_case("box"), "backward-euler", **run)
    try:
        for _ in range(BACKWARD_EULER_CONTACT["steps"]):
            sim.step(1)
            stats = sim.solver_stats
            assert stats.converged and stats.newton_iterations <= 12, (sim.steps, stats)
    finally:
        sim.close()


def contact_case(case, **changes):
    """``ground_sheet(case)`` or ``curved_sheet(case)``."""
    if case in ("slide", "stick", "fall"):
        return ground_sheet(case, **changes)
    return curved_sheet(case, **changes)


def implicit_contact_run(case, path):
    """The implicit contact tests' run: CG to round-off, multigrid on the parallel path.
    The sheets on the ground plane run without the definiteness fix: lying flat, their
    springs pass their rest lengths, where the fix's clamp has a kink (the sliding
    sheet's spring 0 at step 5, |l0/l - 1| = 7e-7) that central differences straddle
    (measured: 1e-6 relative with the fix and 2e-8 without on the sliding sheet, the
    same at steps of 2e-6 and 5e-5; the landing sheet's rest lengths 1.6e-5 at a step of
    1e-5 and 5e-9 at 2e-6)."""
    solver = dict(loops="serial") if path == "serial" else dict(loops="parallel", preconditioner="multigrid")
    if case in ("slide", "stick", "fall"):
        solver["definiteness_fix"] = False
    return dict(steps=30, every=5, dt=2e-3, integrator="implicit", checkpoint=7, cg_tol=1e-13, **solver)


# The parallel path (multigrid) on every sheet; the serial path, whose kernels call the
# same contact functions in other loops, on three (sliding, sticking, curved).
IMPLICIT_CONTACT_CASES = [(case, "parallel") for case in ("slide", "stick", "fall", "sphere", "sphere-stick", "box",
                                                          "groove", "edges")] + \
    [(case, "serial") for case in ("slide", "stick", "sphere")]


@pytest.mark.fast_sample(case_path=[("slide", "serial")])
@pytest.mark.parametrize("case_path", IMPLICIT_CONTACT_CASES, ids=["-".join(pair) for pair in IMPLICIT_CONTACT_CASES])
def test_contact_in_the_implicit_step_has_the_gradient_of_its_branches(case_path):
    """The linearised implicit step's contact constraints and friction
    (``contact.constraint_adjoint``, ``friction.friction_adjoint``; contacts as detected,
    sticking and sliding as decided, frozen), on the explicit tests' sheets: resting and
    sliding or sticking on a plane, landing on it with restitution, on a sphere (sliding
    and sticking), on a box's rounded edge, in a groove of two planes and in one of two
    rounded edges (particles against both: two constraints, and contacts released after
    pulling); the gradient agrees with central differences to 1e-6 relative in every
    parameter kind and the initial state (a sticking sheet: the initial state's only, as
    in the explicit tests). Measured by deleting a piece: the kinetic friction's
    gradient handed to the step before (slide: up to 1.0 relative), the impulse's (slide's
    masses: 1.1), the first contact step's sliding (fall: 0.44), the normals' curvature
    through the directions of friction (sphere: 0.17; the two rounded edges: 2e-2, and
    2e-6 to 4e-5 without the second direction's share through the first)."""
    case, path = case_path
    names = ["positions", "velocities"] if case == "stick" else STILL_AIR
    check_against_differences(lambda **changes: contact_case(case, **changes), names,
                              implicit_contact_run(case, path), along_plane=case in ("slide", "stick"))


def frictionless(model):
    """``model`` with its colliders' friction set to 0."""
    return model.replaced(colliders=[dataclasses.replace(c, friction=0.0) for c in model.colliders])


@pytest.mark.fast_sample(case=["sphere"])
@pytest.mark.parametrize("case", ["slide", "fall", "sphere", "edges"])
def test_frictionless_contact_in_the_implicit_step_has_the_gradient_of_its_branches(case):
    """Without friction the adjoint compiles none of it: the contact constraints alone
    against central differences as above. Measured by deleting a piece: the curvature
    (sphere: up to 9e-2 relative), the impulse's term (sphere: 0.24), the restitution's
    (fall: 0.39), the landing correction (fall: 0.21); not restoring the released
    contacts fails the groove of two planes (up to 8e-5)."""
    check_against_differences(lambda **changes: frictionless(contact_case(case, **changes)), STILL_AIR,
                              implicit_contact_run(case, "serial"), along_plane=case == "slide")


@pytest.mark.fast_sample(integrator=["implicit"])
@pytest.mark.parametrize("integrator", ["implicit", "bdf2"])
def test_checkpointed_gradients_with_contact_equal_those_of_the_stored_trajectory(integrator):
    """``test_gradient``'s checkpointed gradients equal to the stored trajectory's, with
    friction on a sphere (the sheet landing within the run): the contact
    memory kept with each state (released contacts, sticking, kinetic impulses), each
    step's solved velocity, impulses and base, and BDF2's record of which steps used its
    history are those of the forward run when a stretch is run again."""
    model = contact_case("sphere")
    run = dict(steps=30, every=5, dt=2e-3, integrator=integrator, **SOLVED[integrator])
    results = [ms.gradient(model, objective, STILL_AIR, checkpoint=k, **run) for k in (1, 30, 7)]
    for value, grads in results[1:]:
        assert value == results[0][0]
        for name in STILL_AIR:
            np.testing.assert_array_equal(grads[name], results[0][1][name])
