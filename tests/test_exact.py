"""Exact discrete solutions of a one-spring system, and the zero-length rule.

Particle 0 is fixed, particle 1 starts on the spring's axis at distance 1.1 from
it with rest length l0 = 1 and no gravity. Nothing pushes particle 1 off the
axis, so the motion is 1D and, because a spring is linear along its own axis, each
integrator's step is exactly a 2x2 linear map of (u, w), u = |x1 - x0| - l0 the
displacement and w the velocity along the axis:

    explicit:   u' = u + dt w,   w' = w + dt (-ks u - kd w) / m
    symplectic: w' = w + dt (-ks u - kd w) / m,   u' = u + dt w'
    implicit:   (m + dt kd + dt^2 ks) w' = m w - dt ks u,   u' = u + dt w'

(the linearised implicit step of Eq. 15 is exact here: the Jacobian of a linear
force is exact). The simulation must follow these recurrences to round-off.
"""

import numpy as np
import pytest

import massspring as ms
from conftest import PATHS, simulation

KS, KD, M, L0, U0, DT, STEPS = 100.0, 2.0, 1.0, 1.0, 0.1, 1e-2, 200
INTEGRATORS = ("explicit", "symplectic", "implicit")


def recurrence(integrator, steps=STEPS, u=U0, w=0.0):
    """Displacement u_k and velocity w_k, k = 0..steps, of the exact discrete map."""
    us, ws = [u], [w]
    for _ in range(steps):
        if integrator == "explicit":
            u, w = u + DT * w, w + DT * (-KS * u - KD * w) / M
        elif integrator == "symplectic":
            w = w + DT * (-KS * u - KD * w) / M
            u = u + DT * w
        else:
            w = (M * w - DT * KS * u) / (M + DT * KD + DT * DT * KS)
            u = u + DT * w
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
    sim = simulation(model, path, integrator=integrator, dt=DT, precision=precision, cg_tol=cg_tol)
    xs, vs = [sim.positions], [sim.velocities]
    for _ in range(STEPS):
        sim.step()
        xs.append(sim.positions)
        vs.append(sim.velocities)
        if integrator == "implicit":
            assert sim.solver_stats.converged, sim.solver_stats
    assert sim.steps == STEPS and sim.time == pytest.approx(STEPS * DT)
    return np.array(xs), np.array(vs)


# Tolerances. The map is contractive (spectral radius <= 0.995 for all three
# integrators with these parameters), so a local round-off error e per step
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
@pytest.mark.parametrize("integrator", INTEGRATORS)
def test_one_spring_along_x(integrator, precision, path):
    xs, vs = run(spring_model((0, 0, 0), (1, 0, 0)), integrator, precision, CG_TOL[precision], path)
    u, w = recurrence(integrator)
    tol = TOL[precision]
    assert np.max(np.abs(xs[:, 1, 0] - (L0 + u))) <= tol * 1.1
    assert np.max(np.abs(vs[:, 1, 0] - w)) <= tol * 1.0
    # the motion stays on the x axis exactly, the fixed particle does not move
    assert np.all(xs[:, :, 1:] == 0) and np.all(vs[:, :, 1:] == 0)
    assert np.all(xs[:, 0] == 0) and np.all(vs[:, 0] == 0)
    # TOL cannot hide a different scheme: the other recurrences are far away
    # (one step of another scheme differs by ~dt^2 ks u0 = 1e-3)
    for other in INTEGRATORS:
        if other != integrator:
            uo, _ = recurrence(other)
            assert np.max(np.abs(xs[:, 1, 0] - (L0 + uo))) > 30 * tol  # gaps are 0.015-0.04


def random_direction(seed):
    v = np.random.default_rng(seed).normal(size=3)
    return v / np.linalg.norm(v)


@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("integrator", INTEGRATORS)
def test_one_spring_rotated(integrator, path):
    """The same spring along a random unit direction e, anchored off the origin: the
    motion is x1 = x0 + (l0 + u) e with the same (u, w) sequence. Rotation makes the
    unit vector inexact (components rounded), so the along-axis dynamics see a
    relative perturbation of a few eps per step and the transverse direction picks
    up round-off that is not amplified (the transverse stiffness is that of a
    string in tension, or, when compressed and in the implicit step, removed by the
    definiteness fix); the same TOL applies."""
    e = random_direction(7)
    origin = np.array([0.3, -0.2, 0.5])
    xs, vs = run(spring_model(origin, e), integrator, "f64", CG_TOL["f64"], path)
    u, w = recurrence(integrator)
    tol = TOL["f64"]
    assert np.max(np.abs(xs[:, 1] - (origin + np.outer(L0 + u, e)))) <= tol * 1.1
    assert np.max(np.abs(vs[:, 1] - np.outer(w, e))) <= tol
    assert np.all(xs[:, 0] == origin) and np.all(vs[:, 0] == 0)


@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("integrator", INTEGRATORS)
def test_no_springs_free_fall(integrator, path):
    """Without springs every integrator is exact free fall: v_k = v_0 + k dt g, and
    x_k = x_0 + dt sum of v_j over j < k (explicit) or 1 <= j <= k (the others)."""
    g = np.array([0.0, 0.0, -9.81])
    v0 = np.array([1.0, 0.5, 2.0])
    model = ms.Model([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]], np.zeros((0, 2), dtype=int),
                     velocities=[v0, v0], gravity=g, fixed=[1])
    sim = simulation(model, path, integrator=integrator, dt=DT)
    k = 7
    sim.step(k)
    js = np.arange(k) if integrator == "explicit" else np.arange(1, k + 1)
    expected = DT * (k * v0 + DT * js.sum() * g)
    np.testing.assert_allclose(sim.positions[0], expected, rtol=0, atol=1e-14)
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
@pytest.mark.parametrize("integrator", INTEGRATORS)
@pytest.mark.parametrize("separate", [False, True], ids=["coincident", "parting"])
def test_zero_length_springs_stay_finite(integrator, precision, separate, path):
    model = zero_length_model(separate)
    sim = simulation(model, path, integrator=integrator, dt=DT, precision=precision)
    steps = 10
    for _ in range(steps):
        sim.step()
        assert np.all(np.isfinite(sim.positions)) and np.all(np.isfinite(sim.velocities))
        if integrator == "implicit":
            assert np.isfinite(sim.solver_stats.residual)
    if integrator == "implicit":  # with the definiteness fix the solve never fails
        assert sim.cg_failures == 0, sim.solver_stats
    if not separate:
        # Free fall of particles 0..5: a zero-length spring exerts no force; in the
        # implicit matrix only (2, 3)'s l0 = 0 spring adds anything, -ks I acting on
        # v_2 - v_3, which is 0 here.
        # Explicit: x_k = x_0 + dt sum_{j<k} v_j; symplectic and implicit use v_{j+1}.
        g = -9.81
        s = sum(range(steps)) if integrator == "explicit" else sum(range(1, steps + 1))
        expected = model.positions[:6] + [0.0, 0.0, g * DT * DT * s]
        tol = 1e-12 if precision == "f64" else 1e-5
        np.testing.assert_allclose(sim.positions[:6], expected, rtol=0, atol=tol)
        np.testing.assert_allclose(sim.velocities[:6], np.tile([0.0, 0.0, g * DT * steps], (6, 1)),
                                   rtol=0, atol=tol)
