"""Contact with colliders: resting, bouncing, Coulomb friction, moving colliders, cloth on
a sphere and over a box edge, the implicit step's contact constraints against a dense
solve, stiff contact at large dt, and validation of every collider field.

References are analytic (a particle resting, bouncing with restitution e to e^2 times
its drop height, sticking on a plane tilted by theta when tan(theta) < mu and sliding
with acceleration g (sin(theta) - mu cos(theta)) otherwise) or a dense numpy solve of
Eq. 15 with the contact normals' velocities prescribed.
"""

import math

import numpy as np
import pytest

import massspring as ms
from conftest import FULL, PATHS, dense_matrices, simulation
from massspring.integrators import INTEGRATORS as REGISTRY, taken
from massspring.scene import generators

INTEGRATORS = tuple(REGISTRY)  # every integrator takes colliders
G = 9.81
EPS = np.finfo(float).eps
NO_SPRINGS = np.zeros((0, 2), dtype=int)


def particle(x, colliders, v=(0.0, 0.0, 0.0), **kw):
    return ms.Model([x], NO_SPRINGS, masses=0.2, velocities=[v], gravity=(0.0, 0.0, -G), colliders=colliders, **kw)


# ----------------------------------------------------------------------------- one particle


@pytest.mark.fast_sample(integrator=["symplectic", "implicit"])
@pytest.mark.parametrize("integrator", INTEGRATORS)
def test_particle_rests_on_a_plane(integrator):
    """At rest on the ground for 10 s: no penetration, no drift, energy never above its start."""
    model = particle([0.3, -0.2, 0.0], [ms.Plane((0, 0, 0), (0, 0, 1), friction=0.5)])
    sim = ms.Simulation(model, integrator=integrator, dt=0.01)
    e0 = sim.energy()["total"]
    for _ in range(1000):
        sim.step()
        x = sim.positions[0]
        assert x[2] >= -1e-12 and np.abs(x - model.positions[0]).max() <= 1e-12
        assert sim.energy()["total"] <= e0 + 1e-12
    assert np.abs(sim.velocities).max() <= G * 0.01  # at most one step of gravity not yet removed


@pytest.mark.fast_sample(integrator=["symplectic", "implicit"])
@pytest.mark.parametrize("integrator", INTEGRATORS)
def test_particle_rests_on_a_tilted_plane_below_the_friction_angle(integrator):
    mu, theta = 0.6, math.atan(0.5 * 0.6)
    normal = (-math.sin(theta), 0.0, math.cos(theta))
    model = particle([0.0, 0.0, 0.0], [ms.Plane((0, 0, 0), normal, friction=mu)])
    sim = ms.Simulation(model, integrator=integrator, dt=0.01)
    e0 = sim.energy()["total"]
    for _ in range(100):
        sim.step(10)
        assert np.abs(sim.positions[0]).max() <= 1e-12
        assert sim.energy()["total"] <= e0 + 1e-12


@pytest.mark.fast_sample(integrator=["symplectic", "implicit"])
@pytest.mark.parametrize("integrator", INTEGRATORS)
@pytest.mark.parametrize("restitution", [0.0, 0.5, 1.0])
def test_restitution_sets_the_bounce_height(integrator, restitution):
    """Dropped from h = 0.5 m, the particle bounces back to e^2 h: for e = 0 it stays on the
    ground, at rest, from the first impact on. The impact speed v = sqrt(2 g h) is known
    to within a step of gravity, so the apex to within about 2 v dt (plus explicit Euler's
    energy gain in free fall, 1/2 g dt per unit of height)."""
    h, dt = 0.5, 1e-3
    model = particle([0.0, 0.0, h], [ms.Plane((0, 0, 0), (0, 0, 1), restitution=restitution)])
    sim = ms.Simulation(model, integrator=integrator, dt=dt)
    fall = math.sqrt(2 * h / G)
    sim.step(round(1.1 * fall / dt))  # past the first impact
    heights, speeds = [], []
    for _ in range(round(1.7 * fall / dt)):  # up to just before the second impact (for e = 1)
        sim.step()
        heights.append(sim.positions[0, 2])
        speeds.append(sim.velocities[0, 2])
    heights = np.array(heights)
    assert heights.min() >= -1e-12
    tol = 4 * math.sqrt(2 * G * h) * dt
    assert abs(heights.max() - restitution ** 2 * h) <= tol, (heights.max(), restitution ** 2 * h)
    if restitution == 0:
        assert np.all(heights == 0.0) and np.abs(speeds[1:]).max() <= G * dt


@pytest.mark.fast_sample(integrator=["symplectic", "implicit"])
@pytest.mark.parametrize("integrator", INTEGRATORS)
@pytest.mark.parametrize("ratio", [0.9, 1.1])
def test_friction_threshold_on_a_tilted_plane(integrator, ratio):
    """tan(theta) = ratio * mu: at 0.9 the particle sticks (exactly: no creep), at 1.1 it
    slides down the slope with acceleration g (sin(theta) - mu cos(theta)), to within one
    step of gravity in its velocity after 1 s, staying on the plane."""
    mu, dt = 0.4, 1e-3
    theta = math.atan(ratio * mu)
    normal = np.array([-math.sin(theta), 0.0, math.cos(theta)])
    model = particle([0.0, 0.0, 0.0], [ms.Plane((0, 0, 0), normal, friction=mu)])
    sim = ms.Simulation(model, integrator=integrator, dt=dt)
    sim.step(1000)
    x, v = sim.positions[0], sim.velocities[0]
    assert abs(x @ normal) <= 1e-12
    if ratio < 1:
        assert np.abs(x).max() <= 1e-12 and np.abs(v).max() <= G * dt
        return
    downhill = np.array([-math.cos(theta), 0.0, -math.sin(theta)])  # the plane is z = x tan(theta)
    a = G * (math.sin(theta) - mu * math.cos(theta))
    assert abs(v @ downhill - a * 1.0) <= G * dt and abs(v[1]) <= 1e-12
    assert abs(x @ downhill - 0.5 * a) <= G * dt
    # the threshold matters: without friction it would go g sin(theta) / a = 12x faster
    assert G * math.sin(theta) > 10 * a


@pytest.mark.fast_sample(integrator=["symplectic"])
@pytest.mark.parametrize("integrator", INTEGRATORS)
@pytest.mark.parametrize("collider", [
    ms.Plane((0, 0, 0), (0, 0, 1), velocity=(0, 0, 0.5)),
    ms.Sphere((0, 0, -0.4), 0.4, velocity=(0, 0, 0.5)),
    ms.Box((-0.3, -0.3, -0.2), (0.3, 0.3, 0.0), velocity=(0, 0, 0.5)),
], ids=["plane", "sphere", "box"])
def test_a_moving_collider_carries_a_resting_particle(integrator, collider):
    """A collider rising at 0.5 m/s lifts the particle resting on its top: after 1 s the
    particle is 0.5 m higher, moving with it (to within a step of gravity)."""
    dt = 1e-3
    sim = ms.Simulation(particle([0.0, 0.0, 0.0], [collider]), integrator=integrator, dt=dt)
    sim.step(1000)
    assert abs(sim.positions[0, 2] - 0.5) <= G * dt * dt + 1e-12
    assert abs(sim.velocities[0, 2] - 0.5) <= G * dt + 1e-12
    assert np.abs(sim.positions[0, :2]).max() <= 1e-12


@pytest.mark.fast_sample(integrator=["symplectic", "implicit"])
@pytest.mark.parametrize("integrator", INTEGRATORS)
def test_friction_drags_a_particle_along_a_moving_plane(integrator):
    """A conveyor: the ground moves along x at 0.3 m/s under a particle at rest; friction
    (mu = 1) accelerates it at mu g until it moves with the ground (after 0.3 / g s)."""
    dt = 1e-3
    model = particle([0.0, 0.0, 0.0], [ms.Plane((0, 0, 0), (0, 0, 1), friction=1.0, velocity=(0.3, 0, 0))])
    sim = ms.Simulation(model, integrator=integrator, dt=dt)
    sim.step(10)
    assert abs(sim.velocities[0, 0] - G * 10 * dt) <= G * dt  # sliding: mu g t
    sim.step(490)
    np.testing.assert_allclose(sim.velocities[0], [0.3, 0.0, 0.0], rtol=0, atol=G * dt)
    assert abs(sim.positions[0, 2]) <= 1e-12


@pytest.mark.fast_sample(integrator=["symplectic"])
@pytest.mark.parametrize("integrator", INTEGRATORS)
def test_particle_held_in_a_corner_by_wind(integrator):
    """Gravity and wind push a particle into the corner between the ground and a box's side
    (two contact normals at once): it stays in the corner, entering neither."""
    box = ms.Box((0.0, -1.0, -1.0), (1.0, 1.0, 1.0))  # standing in the ground, not on it: see docs/contact.md, Limits
    model = particle([-0.1, 0.0, 0.1], [ms.Plane((0, 0, 0), (0, 0, 1)), box], drag=2.0, wind=(5.0, 0.0, 0.0))
    sim = ms.Simulation(model, integrator=integrator, dt=2e-3)
    sim.step(1500)
    x = sim.positions[0]
    assert x[0] <= 1e-12 and x[2] >= -1e-12
    np.testing.assert_allclose(x, [0.0, 0.0, 0.0], rtol=0, atol=1e-9)


# ----------------------------------------------------------------------------- cloth


def cloth(resolution=8, height=0.5, colliders=(), size=1.0, **kw):
    """A cloth of side ``size``, flat at ``height``, centred over the origin, no pins, in a
    little air drag (so that it settles within a second or two)."""
    args = generators.grid(resolution=resolution, size=size, mass=1.0, stiffness=1e3, damping=5.0, shear=1.0,
                           bend=0.05, pin="none", gravity=[0.0, 0.0, -G])
    args["positions"] = args["positions"] + [-size / 2, -size / 2, height]
    args.update(kw)
    return ms.Model(**args, colliders=list(colliders), drag=0.05)


DT = {name: 1e-2 if cls.traits.linear_solver else 5e-4 for name, cls in REGISTRY.items()}  # implicit steps: no dt limit


@pytest.mark.fast_sample(integrator=["symplectic"])
@pytest.mark.parametrize("integrator", INTEGRATORS)
@pytest.mark.parametrize("ratio", [0.9, 1.5])
def test_cloth_on_a_tilted_plane_sticks_or_slides_as_a_whole(integrator, ratio):
    """Friction on a whole cloth, every particle coupled to its neighbours: lying on a
    plane tilted by theta with tan(theta) = ratio * mu, it stays put (0.9) or its centre
    of mass slides with g (sin(theta) - mu cos(theta)) (1.5), like one particle."""
    mu, theta = 0.3, math.atan(ratio * 0.3)
    normal = np.array([-math.sin(theta), 0.0, math.cos(theta)])
    args = generators.grid(resolution=6, size=0.5, mass=0.5, stiffness=1e3, damping=1.0, shear=1.0, bend=0.1,
                           pin="none", gravity=[0.0, 0.0, -G])
    flat = args["positions"]
    args["positions"] = np.stack([math.cos(theta) * flat[:, 0], flat[:, 1], math.sin(theta) * flat[:, 0]], axis=1)
    model = ms.Model(**args, colliders=[ms.Plane((0, 0, 0), normal, friction=mu)])
    dt = DT[integrator]
    sim = ms.Simulation(model, integrator=integrator, dt=dt)
    sim.step(round(0.5 / dt))
    downhill = np.array([-math.cos(theta), 0.0, -math.sin(theta)])
    speed = sim.velocities.mean(axis=0) @ downhill
    assert np.abs(sim.positions @ normal).max() <= 1e-12
    if ratio < 1:
        assert np.abs(sim.positions - model.positions).max() <= 1e-12
    else:
        a = G * (math.sin(theta) - mu * math.cos(theta))
        assert abs(speed - 0.5 * a) <= G * dt, (speed, 0.5 * a)


@pytest.mark.fast_sample(integrator=["symplectic"])
@pytest.mark.parametrize("integrator", INTEGRATORS)
def test_cloth_drapes_over_a_sphere(integrator):
    """After 2 s the cloth rests on the sphere: no vertex deeper inside than 1e-3 of the
    radius, the middle lying on the top, the edges hanging below the sphere's centre.
    The sphere's friction 1.0 holds it: with 0.5 the hanging edges drag the cloth off
    the sphere, creeping at 2 s (0.05 m/s, so "settled" then depended on the CPU's
    rounding) and sliding off by 2.7 s with backward Euler."""
    radius = 0.3
    model = cloth(size=1.2, colliders=[ms.Plane((0, 0, -0.35), (0, 0, 1), friction=0.5),
                                       ms.Sphere((0, 0, 0), radius, friction=1.0)])
    sim = ms.Simulation(model, integrator=integrator, dt=DT[integrator])
    sim.step(round(2.0 / DT[integrator]))
    x = sim.positions
    gap = np.linalg.norm(x, axis=1) - radius
    assert gap.min() >= -1e-3 * radius
    middle = np.argsort(np.linalg.norm(x[:, :2], axis=1))[:4]
    assert np.all(np.abs(gap[middle]) <= 1e-3 * radius)  # the middle lies on the sphere
    assert x[:, 2].min() < -0.01  # the edges hang below the equator
    assert x[:, 2].min() >= -0.35 - 1e-12  # above the ground
    assert np.abs(sim.velocities).max() < 0.05  # settled


@pytest.mark.fast_sample(integrator=["symplectic"])
@pytest.mark.parametrize("integrator", INTEGRATORS)
@pytest.mark.parametrize("mu", [0.8, 0.0])
def test_cloth_bends_over_a_box_edge(integrator, mu):
    """A cloth falling on a box so that half of it overhangs: no vertex enters the box, the
    overhang hangs down past the edge, outside the box's side; friction 0.8 holds the
    cloth on the top (it bends over the edge), without friction it slides off within 1 s."""
    box = ms.Box((-1.0, -1.0, -1.0), (0.0, 1.0, 0.0), friction=mu)
    model = cloth(height=0.1, colliders=[box])
    sim = ms.Simulation(model, integrator=integrator, dt=DT[integrator])
    sim.step(round(1.0 / DT[integrator]))
    x = sim.positions
    depth = np.min(np.concatenate([x - box.lower, box.upper - x], axis=1), axis=1)  # > 0 inside
    assert depth.max() <= 1e-3
    assert x[:, 2].min() < -0.5  # the overhang hangs down past the edge
    assert x[x[:, 2] < -0.05, 0].min() >= -1e-3  # ... outside the box's side
    if mu > 0:
        assert x[:, 0].min() < -0.45  # held on the top by friction
        assert np.abs(x[x[:, 0] < -0.3, 2]).max() <= 1e-3  # lying on it
    else:
        assert x[:, 0].min() > -0.1  # slid off


@pytest.mark.fast_sample(integrator=["symplectic", "implicit"])
@pytest.mark.parametrize("integrator", INTEGRATORS)
def test_particle_rests_on_a_rounded_box_edge(integrator):
    """A box with rounded edges (radius r): a particle dropped on the top edge line stays
    (friction 2) on the rounding, at the distance r from the box's inner edge, off the
    sharp box's corner point."""
    r = 0.1
    box = ms.Box((-1.0, -1.0, -1.0), (0.0, 1.0, 0.0), radius=r, friction=2.0)
    sim = ms.Simulation(particle([-0.03, 0.0, 0.2], [box]), integrator=integrator, dt=1e-3)
    sim.step(1000)
    x = sim.positions[0]
    assert abs(np.hypot(x[0] + r, x[2] + r) - r) <= 1e-9 and x[2] < -1e-3
    assert np.abs(sim.velocities).max() <= G * 1e-3


@pytest.mark.full
def test_stiff_contact_at_large_dt_stays_bounded_or_diverges_cleanly():
    """A very stiff cloth (1e6 N/m) dropped flat on the ground: the implicit step at
    dt = 0.05 never lets a particle below it and ends (2 s) in the exact resting state,
    flat on the ground, still, every spring at its rest length; symplectic Euler at 20x
    its stability limit raises DivergenceError and keeps its last good state."""
    model = cloth(resolution=6, height=0.2, colliders=[ms.Plane((0, 0, 0), (0, 0, 1), friction=0.3)],
                  stiffness=1e6)
    sim = ms.Simulation(model, integrator="implicit", dt=0.05)
    for _ in range(40):
        sim.step()
        assert np.all(np.isfinite(sim.positions)) and sim.positions[:, 2].min() >= -1e-9
    np.testing.assert_allclose(sim.positions[:, 2], 0.0, rtol=0, atol=1e-9)
    np.testing.assert_allclose(sim.positions[:, :2], model.positions[:, :2], rtol=0, atol=1e-9)
    assert np.abs(sim.velocities).max() <= 1e-9
    from massspring.analysis.stability import predict

    dt = 20 * predict(model).symplectic_dt
    sim = ms.Simulation(model, integrator="symplectic", dt=dt)
    with pytest.raises(ms.DivergenceError) as info:
        sim.step(10_000)
    assert sim.steps == info.value.step - 1 and info.value.step < 10_000
    assert np.all(np.isfinite(sim.positions)) and np.all(np.isfinite(sim.velocities))
    assert sim.positions[:, 2].min() >= -1e-9


@FULL
@pytest.mark.parametrize("integrator", ["explicit", "implicit", "rk4"])
def test_serial_and_parallel_drivers_agree_with_colliders(integrator):
    model = cloth(resolution=6, colliders=[ms.Plane((0, 0, -0.35), (0, 0, 1), friction=0.5),
                                           ms.Sphere((0, 0, 0), 0.3, friction=0.5, velocity=(0.1, 0, 0)),
                                           ms.Box((0.4, -1, -1), (1, 1, 0.1), friction=0.2)])
    dt = DT[integrator]
    out = []
    for path in PATHS:
        sim = simulation(model, path, integrator=integrator, dt=dt, **taken(integrator, {"cg_tol": 1e-12}))
        sim.step(round(0.4 / dt))  # the cloth is on the sphere from 0.3 s on
        out.append(sim.positions)
    np.testing.assert_allclose(out[0], out[1], rtol=0, atol=1e-9)


# ----------------------------------------------------------------------------- the implicit step


def rotated_reference(model, dt, contacts):
    """v' of Eq. 15 with the velocity of particle i along unit n_i prescribed to u_i for each
    (i, n_i, u_i) of ``contacts`` and the pins' velocities prescribed, by a dense solve in
    per-particle bases whose third axis is n_i (unknowns y = Q^T v)."""
    A, b = dense_matrices(model, dt, True)
    size = 3 * model.n_particles
    Q = np.eye(size)
    prescribed = {}
    for i, n, u in contacts:
        t1 = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
        t1 /= np.linalg.norm(t1)
        Q[3 * i:3 * i + 3, 3 * i:3 * i + 3] = np.stack([t1, np.cross(n, t1), n], axis=1)
        prescribed[3 * i + 2] = u
    for i, v in zip(model.fixed, model.pin_velocity):
        for axis in range(3):
            prescribed[3 * i + axis] = v[axis]
    fixed = np.zeros(size, dtype=bool)
    y = np.zeros(size)
    for dof, value in prescribed.items():
        fixed[dof], y[dof] = True, value
    A, b = Q.T @ A @ Q, Q.T @ b
    y[~fixed] = np.linalg.solve(A[np.ix_(~fixed, ~fixed)], b[~fixed] - A[np.ix_(~fixed, fixed)] @ y[fixed])
    return (Q @ y).reshape(-1, 3), A[np.ix_(~fixed, ~fixed)]


@pytest.mark.fast_sample(path=["serial"])
@pytest.mark.parametrize("path", PATHS)
def test_implicit_contact_step_matches_dense_solve(path):
    """A cloth whose first two rows lie on a tilted plane and move into it, the others
    lifted off it, one of them pinned and moving: one implicit step (friction 0,
    restitution 0.5) solves Eq. 15 with each touching particle's normal velocity
    prescribed to e times the speed it arrives with, and its other directions free."""
    theta, e, dt = 0.3, 0.5, 0.02
    normal = np.array([-math.sin(theta), 0.0, math.cos(theta)])
    args = generators.grid(resolution=4, size=0.6, mass=0.5, stiffness=300.0, damping=1.5, shear=1.0, bend=0.1,
                           pin="none", gravity=[0.0, 0.0, -G])
    flat = args["positions"]
    slope = np.stack([math.cos(theta) * flat[:, 0], flat[:, 1], math.sin(theta) * flat[:, 0]], axis=1)
    rows = np.arange(16) // 4
    lifted = rows >= 2
    x = slope + np.where(lifted, 0.3, 0.0)[:, None] * normal
    rng = np.random.default_rng(11)
    v = rng.normal(scale=0.3, size=(16, 3))
    v -= np.where(lifted, 0.0, np.abs(rng.normal(size=16)) + (v @ normal))[:, None] * normal  # into the plane
    model = ms.Model(x, args["springs"], masses=args["masses"], stiffness=args["stiffness"],
                     damping=args["damping"], rest_lengths=args["rest_lengths"], velocities=v,
                     gravity=(0.0, 0.0, -G), fixed=[15], pin_velocity=[[0.2, 0.1, 0.0]],
                     colliders=[ms.Plane((0, 0, 0), normal, restitution=e)])
    touching = np.flatnonzero(~lifted)
    contacts = [(i, normal, -e * (model.velocities[i] @ normal)) for i in touching]
    v_ref, A = rotated_reference(model, dt, contacts)
    sim = simulation(model, path, integrator="implicit", dt=dt, cg_tol=1e-12)
    sim.step()
    assert sim.solver_stats.converged
    bound = np.linalg.cond(A) * 1e-11 * np.linalg.norm(v_ref)
    assert np.linalg.norm(sim.velocities - v_ref) <= bound
    np.testing.assert_allclose(sim.velocities[touching] @ normal, [u for _, _, u in contacts], rtol=0, atol=1e-12)
    np.testing.assert_allclose(sim.positions, x + dt * sim.velocities, rtol=0, atol=1e-14)
    # the constraints matter: without the plane the step is far away
    free, _ = rotated_reference(model, dt, [])
    assert np.linalg.norm(free - v_ref) > 1e3 * bound


# ----------------------------------------------------------------------------- validation


@pytest.mark.parametrize("make, field", [
    (lambda: ms.Plane((0, 0, math.nan), (0, 0, 1)), "point"),
    (lambda: ms.Plane((0, 0), (0, 0, 1)), "point"),
    (lambda: ms.Plane((0, 0, 0), (0, 0, 0)), "normal"),
    (lambda: ms.Plane((0, 0, 0), (0, math.inf, 1)), "normal"),
    (lambda: ms.Plane((0, 0, 0), "up"), "normal"),
    (lambda: ms.Plane((0, 0, 0), (0, 0, 1), friction=-0.1), "friction"),
    (lambda: ms.Plane((0, 0, 0), (0, 0, 1), friction=math.nan), "friction"),
    (lambda: ms.Plane((0, 0, 0), (0, 0, 1), restitution=1.5), "restitution"),
    (lambda: ms.Plane((0, 0, 0), (0, 0, 1), restitution=-0.5), "restitution"),
    (lambda: ms.Plane((0, 0, 0), (0, 0, 1), velocity=(1, 2)), "velocity"),
    (lambda: ms.Sphere((0, 0, 0), 0.0), "radius"),
    (lambda: ms.Sphere((0, 0, 0), -1.0), "radius"),
    (lambda: ms.Sphere((0, 0, 0), [1.0, 2.0]), "radius"),
    (lambda: ms.Sphere((0, 0, "1"), 1.0), "center"),
    (lambda: ms.Sphere((0, 0, 0), 1.0, friction="high"), "friction"),
    (lambda: ms.Box((0, 0, 0), (1, 1, 0)), "lower"),
    (lambda: ms.Box((0, 2, 0), (1, 1, 1)), "lower"),
    (lambda: ms.Box((0, 0, 0), (1, 1, math.inf)), "upper"),
    (lambda: ms.Box((0, 0, 0), (1, 1, 1), velocity=(0, math.nan, 0)), "velocity"),
    (lambda: ms.Box((0, 0, 0), (1, 1, 1), radius=-0.1), "radius"),
    (lambda: ms.Box((0, 0, 0), (1, 1, 0.1), radius=0.06), "radius"),
])
def test_bad_collider_fields_are_named(make, field):
    with pytest.raises(ValueError) as info:
        make()
    assert str(info.value).startswith(field + ":"), info.value


def test_colliders_are_validated_normalised_and_frozen():
    plane = ms.Plane([0, 0, 1], [0, 0, 2], friction=1, restitution=0)
    assert plane.normal == (0.0, 0.0, 1.0) and plane.point == (0.0, 0.0, 1.0) and plane.friction == 1.0
    with pytest.raises(Exception):
        plane.friction = 0.5
    moved = ms.Box((0, 0, 0), (1, 1, 1), velocity=(1, 0, 0)).at(2.0)
    assert moved.lower == (2.0, 0.0, 0.0) and moved.upper == (3.0, 1.0, 1.0)
    for bad in ([plane, "sphere"], plane, [plane] * 32):
        with pytest.raises(ValueError) as info:
            particle([0, 0, 1], bad)
        assert str(info.value).startswith("colliders:")
    assert particle([0, 0, 1], (plane,)).colliders == (plane,)


def test_a_model_without_colliders_has_no_contact_arrays():
    plain = ms.Simulation(cloth(resolution=3), integrator="implicit").info()
    assert not [a for a in plain["arrays"] if a.startswith(("plane", "sphere", "box", "c", "released", "impulse"))
                and a != "coef"]
    assert not [t for t in plain["terms"] if t.startswith("contact")]
    touched = ms.Simulation(cloth(resolution=3, colliders=[ms.Sphere((0, 0, 0), 0.2)]), integrator="implicit")
    info = touched.info()
    assert {"sphere_center", "sphere_radius", "cfilter", "contacts", "released"} <= set(info["arrays"])
    assert not [a for a in info["arrays"] if a.startswith(("plane", "box"))]
    assert "contact (sphere)" in info["terms"]
    explicit = ms.Simulation(cloth(resolution=3, colliders=[ms.Sphere((0, 0, 0), 0.2)]), integrator="explicit")
    assert "cfilter" not in explicit.info()["arrays"]  # the filter is the implicit step's


def test_plane_normals_of_any_scale_are_normalised():
    assert ms.Plane((0, 0, 0), (1e-200, 0, 0)).normal == (1.0, 0.0, 0.0)  # its plain norm underflows to 0
    assert ms.Plane((0, 0, 0), (3e90, 0, 4e90)).normal == pytest.approx((0.6, 0.0, 0.8), rel=1e-15)
    with pytest.raises(ValueError, match="normal: must be a non-zero vector"):
        ms.Plane((0, 0, 0), (0.0, -0.0, 0.0))


@pytest.mark.parametrize("collider, point, distance", [
    (ms.Plane((0, 0, 1), (0, 0, 2)), (3.0, -1.0, 0.0), -1.0),
    (ms.Sphere((1, 1, 1), 0.5), (1.0, 1.0, 3.0), 1.5),
    (ms.Sphere((1, 1, 1), 0.5), (1.0, 1.2, 1.0), -0.3),
    (ms.Box((0, 0, 0), (2, 2, 2)), (1.0, 1.0, 2.5), 0.5),        # above a face
    (ms.Box((0, 0, 0), (2, 2, 2)), (3.0, 3.0, 1.0), math.sqrt(2)),  # off an edge
    (ms.Box((0, 0, 0), (2, 2, 2)), (1.0, 1.0, 1.8), -0.2),       # inside, nearest the top
    (ms.Box((0, 0, 0), (2, 2, 2), radius=0.5), (2.5, 2.5, 1.0), math.sqrt(2) - 0.5),  # off a rounded edge
])
def test_signed_distance_of_each_collider(collider, point, distance):
    assert collider.signed_distance([point])[0] == pytest.approx(distance, abs=1e-12)


def test_a_particle_starting_inside_a_collider_is_refused_naming_it():
    x = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 0.0], [0.0, 0.5, -0.25]])
    springs = np.array([[0, 1], [1, 2]])
    ground = ms.Plane((0, 0, 0), (0, 0, 1))
    with pytest.raises(ValueError, match=r"colliders: item 1 \(plane\) holds 1 free particle\(s\) at the start, "
                                         r"particle 2 0.25 m deep"):
        ms.Model(x, springs, colliders=[ms.Sphere((5, 5, 5), 1), ground])
    ms.Model(x, springs, fixed=[2], colliders=[ground])  # a pin may sit in it; touching (particle 1) is fine


@FULL
def test_a_cloth_dragging_a_particle_at_a_crawl_is_smooth_in_its_parameters():
    """The sheets scene without self-collision, implicit at 1/60 s: the lower sheet lands
    on the sphere and drags a particle over it at about 1e-3 m/s against a kinetic
    friction impulse of 0.5 m/s a step, which then sticks (the damper could hold it)
    instead of sliding on with its friction's direction taken from a velocity at
    round-off, which made any change grow 30-fold a step. So the run is smooth in the
    springs' stiffness over 40 steps: central differences with steps of 1e-6 and 1e-8
    agree to 1e-4 (before: 55 and 2,287 at 30 steps), and the gradient (``ms.gradient``)
    agrees with them to 1e-5."""
    base = ms.load_scene("sheets").with_params(resolution=6).model().replaced(self_collision=None)
    target = np.random.default_rng(0).normal(size=(base.n_particles, 3))
    run = dict(steps=40, every=40, dt=1 / 60, integrator="implicit", cg_tol=1e-13)

    def value(scale):
        sim = ms.Simulation(base.replaced(stiffness=base.stiffness * scale), "implicit", dt=1 / 60, cg_tol=1e-13)
        sim.step(run["steps"])
        out = float(np.sum(sim.positions * target))
        sim.close()
        return out

    def objective(frames):
        partial = np.zeros_like(frames.positions)
        partial[-1] = target
        return float(np.sum(frames.positions[-1] * target)), {"positions": partial}

    coarse, fine = ((value(0.7 + d) - value(0.7 - d)) / (2 * d) for d in (1e-6, 1e-8))
    assert abs(coarse - fine) <= 1e-4 * abs(coarse)
    _, grads = ms.gradient(base.replaced(stiffness=base.stiffness * 0.7), objective, "stiffness", **run)
    exact = float(np.sum(grads["stiffness"] * base.stiffness))
    assert abs(exact - coarse) <= 1e-5 * abs(coarse), (exact, coarse, fine)
