"""Exact discrete solutions of a one-spring system, and the zero-length rule.

Particle 0 is fixed, particle 1 starts on the spring's axis at distance 1.1 from
it with rest length l0 = 1 and no gravity. Nothing pushes particle 1 off the
axis, so the motion is 1D and, because a spring is linear along its own axis, each
integrator's step is exactly a 2x2 linear map of (u, w), u = |x1 - x0| - l0 the
displacement and w the velocity along the axis:

    explicit:   u' = u + dt w,   w' = w + dt a(u, w),   a(u, w) = (-ks u - kd w) / m
    symplectic: w' = w + dt a(u, w),   u' = u + dt w'
    implicit:   (m + dt kd + dt^2 ks) w' = m w - dt ks u,   u' = u + dt w'
                (w' = w + dt a(u', w'): backward Euler, I(u, w; dt) below)
    backward-euler: the same map
    bdf2:       I(4/3 u - 1/3 u_prev, 4/3 w - 1/3 w_prev; 2 dt / 3); the first step I(u, w; dt)
    midpoint:   (u + dt/2 wm, wm) = I(u, w; dt/2) is the midpoint and the mean velocity
                wm = (w + w')/2 (w' - w = dt a(u + dt/2 wm, wm)), so w' = 2 wm - w, u' = u + dt wm
    rk4:        y' = y + dt/6 (k1 + 2 k2 + 2 k3 + k4) for y = (u, w), dy/dt = (w, a(u, w))

(the linearised implicit step of Eq. 15 is exact here: the Jacobian of a linear
force is exact; so a Newton-solved step's first iteration solves its equations, and
the next finds nothing left to do). The simulation must follow these recurrences to
round-off. An integrator without a recurrence here fails the tests that need one:
derive its map of this linear system and add it to ``recurrence``.
"""

import numpy as np
import pytest

import massspring as ms
from massspring.integrators import INTEGRATORS, taken
from conftest import PATHS, simulation

KS, KD, M, L0, U0, DT, STEPS = 100.0, 2.0, 1.0, 1.0, 0.1, 1e-2, 200
ALIKE = {"backward-euler": "implicit"}  # integrators whose map of a linear force is another's


def implicit_map(u, w, h, ks, kd, g):
    """I(u, w; h): backward Euler's step of size h from (u, w), w' = w + h a(u + h w', w')
    with a(u, w) = (-ks u - kd w) / m + g, solved (one linear equation), u' = u + h w'."""
    w = (M * w - h * ks * u + h * M * g) / (M + h * kd + h * h * ks)
    return u + h * w, w


def recurrence(integrator, steps=STEPS, u=U0, w=0.0, ks=KS, kd=KD, g=0.0):
    """Displacement u_k and velocity w_k, k = 0..steps, of the exact discrete map (under a
    constant acceleration g besides the spring; u, w and g may be arrays: component-wise)."""
    scheme = ALIKE.get(integrator, integrator)

    def a(u, w):
        return (-ks * u - kd * w) / M + g

    us, ws = [u], [w]
    for _ in range(steps):
        if scheme == "explicit":
            u, w = u + DT * w, w + DT * a(u, w)
        elif scheme == "symplectic":
            w = w + DT * a(u, w)
            u = u + DT * w
        elif scheme == "implicit":
            u, w = implicit_map(u, w, DT, ks, kd, g)
        elif scheme == "bdf2":
            if len(us) == 1:
                u, w = implicit_map(u, w, DT, ks, kd, g)
            else:
                u, w = implicit_map(4 / 3 * u - 1 / 3 * us[-2], 4 / 3 * w - 1 / 3 * ws[-2], 2 * DT / 3, ks, kd, g)
        elif scheme == "midpoint":
            _, mean = implicit_map(u, w, DT / 2, ks, kd, g)
            u, w = u + DT * mean, 2 * mean - w
        elif scheme == "rk4":
            k1 = (w, a(u, w))
            k2 = (w + DT / 2 * k1[1], a(u + DT / 2 * k1[0], w + DT / 2 * k1[1]))
            k3 = (w + DT / 2 * k2[1], a(u + DT / 2 * k2[0], w + DT / 2 * k2[1]))
            k4 = (w + DT * k3[1], a(u + DT * k3[0], w + DT * k3[1]))
            u, w = (y + DT / 6 * (d1 + 2 * d2 + 2 * d3 + d4) for y, d1, d2, d3, d4 in zip((u, w), k1, k2, k3, k4))
        else:
            raise KeyError(f"no exact discrete map for the integrator {integrator!r}: derive it in recurrence()")
        us.append(u)
        ws.append(w)
    return np.array(us), np.array(ws)


def test_recurrences_are_stable_oscillations():
    """The parameters give a damped oscillation for every integrator: the comparison
    below is on a well-conditioned trajectory that neither blows up nor dies out."""
    for integrator in INTEGRATORS:
        u, w = recurrence(integrator)
        assert np.all(np.abs(u) <= U0 * 1.0001)
        assert np.sum(np.diff(np.sign(u)) != 0) >= 4  # several half periods
        assert 0.01 * U0 < np.abs(u[-40:]).max()


def spring_model(origin, direction):
    x0 = np.asarray(origin, dtype=np.float64)
    x1 = x0 + (L0 + U0) * np.asarray(direction, dtype=np.float64)
    return ms.Model([x0, x1], [[0, 1]], masses=M, stiffness=KS, damping=KD, rest_lengths=L0,
                    gravity=(0.0, 0.0, 0.0), fixed=[0])


def run(model, integrator, precision, cg_tol, path):
    """Positions and velocities of both particles after each of STEPS steps."""
    sim = simulation(model, path, integrator=integrator, dt=DT, precision=precision,
                     **taken(integrator, {"cg_tol": cg_tol}))
    xs, vs = [sim.positions], [sim.velocities]
    for _ in range(STEPS):
        sim.step()
        xs.append(sim.positions)
        vs.append(sim.velocities)
        if INTEGRATORS[integrator].traits.has_stats:
            assert sim.solver_stats.converged, sim.solver_stats
    assert sim.steps == STEPS and sim.time == pytest.approx(STEPS * DT)
    return np.array(xs), np.array(vs)


# Tolerances. The map is contractive (spectral radius <= 0.995 for every integrator
# with these parameters: 0.985 implicit and backward Euler, 0.990 symplectic, BDF2,
# midpoint and RK4, 0.995 explicit), so a local round-off error e per step
# accumulates to at most about STEPS * e. One step rounds a few operations on
# numbers of size |x| <= 1.1, |w| <= 1, ks |u| <= 10 (times dt), i.e. e is a few
# units of eps * 1.1. STEPS * 10 * eps bounds the total error with a margin:
# f64: 200 * 10 * 2.2e-16 = 4.4e-13 (the brief's "1e-12 relative" scale);
# f32: 200 * 10 * 1.2e-7 = 2.4e-4, plus the f32 rounding of the inputs
# (1.1, dt: relative 6e-8, a phase error of 20 rad * 6e-8 = 1.2e-6 after 200
# steps) which is far below it. Errors are measured relative to the amplitude
# scales 1.1 (positions) and 1 (velocities: w peaks at about omega u0 = 1).
TOL = {"f64": STEPS * 10 * np.finfo(np.float64).eps, "f32": STEPS * 10 * np.finfo(np.float32).eps}
CG_TOL = {"f64": 1e-12, "f32": 1e-5}


@pytest.mark.fast_sample(integrator=["symplectic", "implicit"], precision=["f64"], path=["serial"])
@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("precision", ["f64", "f32"])
@pytest.mark.parametrize("integrator", tuple(INTEGRATORS))
def test_one_spring_along_x(integrator, precision, path):
    xs, vs = run(spring_model((0, 0, 0), (1, 0, 0)), integrator, precision, CG_TOL[precision], path)
    u, w = recurrence(integrator)
    tol = TOL[precision]
    assert np.max(np.abs(xs[:, 1, 0] - (L0 + u))) <= tol * 1.1
    assert np.max(np.abs(vs[:, 1, 0] - w)) <= tol * 1.0
    # the motion stays on the x axis exactly, the fixed particle does not move
    assert np.all(xs[:, :, 1:] == 0) and np.all(vs[:, :, 1:] == 0)
    assert np.all(xs[:, 0] == 0) and np.all(vs[:, 0] == 0)
    # TOL cannot hide a different scheme: the other recurrences are far away (one step of
    # another scheme differs by ~dt^2 ks u0 = 1e-3; after 200 steps the schemes differ by
    # 3.1e-4 (midpoint and RK4, the closest), 9.4e-4 (BDF2 and midpoint), 1.2e-3 (BDF2 and
    # RK4), 5e-3 to 5.7e-3 (these three and symplectic), 0.0145-0.04 (the others). f32's
    # TOL (2.4e-4) tells only the last apart by 30 TOL: the f64 cases check every pair.
    for other in INTEGRATORS:
        uo, _ = recurrence(other)
        if ALIKE.get(other, other) == ALIKE.get(integrator, integrator):
            continue
        if precision == "f64" or np.max(np.abs(uo - u)) > 30 * tol:
            assert np.max(np.abs(xs[:, 1, 0] - (L0 + uo))) > 30 * tol


FREE_FALL_SUMS = {  # the j of the sum of v_j = v_0 + j dt g over which x_k = x_0 + dt sum v_j in free fall
    "explicit": lambda k: np.arange(k),
    "symplectic": lambda k: np.arange(1, k + 1),
    "implicit": lambda k: np.arange(1, k + 1),
    "midpoint": lambda k: np.arange(k) + 0.5,  # (v_j + v_{j+1}) / 2 = v_{j + 1/2}
    "rk4": lambda k: np.arange(k) + 0.5,
}


def random_direction(seed):
    v = np.random.default_rng(seed).normal(size=3)
    return v / np.linalg.norm(v)


@pytest.mark.fast_sample(integrator=["symplectic", "implicit"], path=["serial"])
@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("integrator", tuple(INTEGRATORS))
def test_one_spring_rotated(integrator, path):
    """The same spring along a random unit direction e, anchored off the origin: the
    motion is x1 = x0 + (l0 + u) e with the same (u, w) sequence. Rotation makes the
    unit vector inexact (components rounded), so the along-axis dynamics see a
    relative perturbation of a few eps per step and the transverse direction picks
    up round-off that is not amplified (the transverse stiffness is that of a
    string in tension, or, when compressed and in the implicit step, removed by the
    definiteness fix); the same TOL applies. The fixed particle stays exactly where it
    is, not an ulp off (BDF2 once based a pin on (4 x_n - x_{n-1}) / 3), and its velocity
    is exactly 0."""
    e = random_direction(7)
    origin = np.array([0.3, -0.2, 0.5])
    xs, vs = run(spring_model(origin, e), integrator, "f64", CG_TOL["f64"], path)
    u, w = recurrence(integrator)
    tol = TOL["f64"]
    assert np.max(np.abs(xs[:, 1] - (origin + np.outer(L0 + u, e)))) <= tol * 1.1
    assert np.max(np.abs(vs[:, 1] - np.outer(w, e))) <= tol
    assert np.all(vs[:, 0] == 0)
    np.testing.assert_array_equal(xs[:, 0], np.broadcast_to(origin, xs[:, 0].shape))


@pytest.mark.fast_sample(integrator=["symplectic", "implicit"], path=["serial"])
@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("integrator", tuple(INTEGRATORS))
def test_no_springs_free_fall(integrator, path):
    """Without springs every integrator is exact free fall: v_k = v_0 + k dt g, and x_k =
    x_0 + dt sum of v_j over j < k (explicit), 1 <= j <= k (symplectic, implicit, backward
    Euler), of (v_j + v_{j+1})/2 over j < k (midpoint and RK4: exact, x_0 + k dt v_0 + (k
    dt)^2 g / 2), or BDF2's recurrence (its ``recurrence`` with no spring)."""
    g = np.array([0.0, 0.0, -9.81])
    v0 = np.array([1.0, 0.5, 2.0])
    model = ms.Model([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]], np.zeros((0, 2), dtype=int),
                     velocities=[v0, v0], gravity=g, fixed=[1])
    sim = simulation(model, path, integrator=integrator, dt=DT)
    k = 7
    sim.step(k)
    us, _ = recurrence(integrator, steps=k, u=np.zeros(3), w=v0, ks=0.0, kd=0.0, g=g)
    if ALIKE.get(integrator, integrator) in FREE_FALL_SUMS:  # the recurrence agrees with the sums above
        js = FREE_FALL_SUMS[ALIKE.get(integrator, integrator)](k)
        np.testing.assert_allclose(us[-1], DT * (k * v0 + DT * js.sum() * g), rtol=0, atol=1e-15)
    np.testing.assert_allclose(sim.positions[0], us[-1], rtol=0, atol=1e-14)
    np.testing.assert_allclose(sim.velocities[0], v0 + k * DT * g, rtol=0, atol=1e-14)
    assert np.all(sim.positions[1] == [1.0, 0.0, 0.0]) and np.all(sim.velocities[1] == 0)


# ----------------------------------------------------------------------------- zero length


def zero_length_model(separate):
    """Pair (0, 1) coincident with l0 = 0.5, pair (2, 3) coincident with l0 = 0 and
    pair (4, 5) 1e-13 apart (below the f64 zero-length threshold 1e-12) with l0 = 0.3,
    under gravity; particle 7 is fixed and holds particle 6 by a spring.

    ``separate=False``: the pairs are otherwise free and start at rest, so by the
    zero-length rule they stay together and fall freely, every step through the
    zero-length branch. ``separate=True``: the coincident particles get different
    velocities and 0, 2, 4 are also tied to 6 and 7, so the pairs part after one
    step and their springs act from very short lengths (large compressions)."""
    x = np.zeros((8, 3))
    x[2:4] = [1.0, 0.0, 0.0]
    x[4] = [0.0, 1.0, 0.0]
    x[5] = [0.0, 1.0, 1e-13]
    x[6] = [0.5, 0.5, 0.0]
    x[7] = [0.0, 2.0, 0.0]
    springs = [[0, 1], [2, 3], [4, 5], [7, 6]]
    rest = [0.5, 0.0, 0.3, 1.5]
    v = np.zeros((8, 3))
    if separate:
        springs += [[6, 0], [6, 2], [7, 4]]
        rest += [0.7, 0.7, 1.0]
        v[1] = [0.0, 0.3, -0.1]
        v[3] = [0.2, 0.0, 0.0]
        v[5] = [0.1, 0.1, 0.1]
    return ms.Model(x, springs, masses=1.0, stiffness=50.0, damping=0.5, rest_lengths=rest,
                    velocities=v, gravity=(0.0, 0.0, -9.81), fixed=[7])


@pytest.mark.fast_sample(integrator=["symplectic", "implicit"], precision=["f32"], path=["serial"])
@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("precision", ["f64", "f32"])
@pytest.mark.parametrize("integrator", tuple(INTEGRATORS))
@pytest.mark.parametrize("separate", [False, True], ids=["coincident", "parting"])
def test_zero_length_springs_stay_finite(integrator, precision, separate, path):
    model = zero_length_model(separate)
    sim = simulation(model, path, integrator=integrator, dt=DT, precision=precision)
    steps = 10
    solved = INTEGRATORS[integrator].traits.has_stats
    for _ in range(steps):
        sim.step()
        assert np.all(np.isfinite(sim.positions)) and np.all(np.isfinite(sim.velocities))
        if solved:
            assert np.isfinite(sim.solver_stats.residual)
    if solved:  # with the definiteness fix the solve never fails
        assert sim.cg_failures == 0, sim.solver_stats
    if not separate:
        # Free fall of particles 0..5: a zero-length spring exerts no force; in the
        # implicit matrix only (2, 3)'s l0 = 0 spring adds anything, -ks I acting on
        # v_2 - v_3, which is 0 here.
        # The free-fall recurrence of each integrator (``test_no_springs_free_fall``).
        g = -9.81
        fall, _ = recurrence(integrator, steps=steps, u=0.0, w=0.0, ks=0.0, kd=0.0, g=g)
        expected = model.positions[:6] + [0.0, 0.0, fall[-1]]
        tol = 1e-12 if precision == "f64" else 1e-5
        np.testing.assert_allclose(sim.positions[:6], expected, rtol=0, atol=tol)
        np.testing.assert_allclose(sim.velocities[:6], np.tile([0.0, 0.0, g * DT * steps], (6, 1)),
                                   rtol=0, atol=tol)
