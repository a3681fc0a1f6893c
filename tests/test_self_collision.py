"""Self-collision (massspring/passes/self_collision/__init__.py, kernels/self_collision.py): the mesh never
passes through itself, checked by a crossing counter written here in numpy (not the
project's detection), the narrow phase against sampled distances, validation,
determinism and restart."""

import dataclasses
import os
import subprocess
import sys

import numpy as np
import pytest
import taichi as ti

import massspring as ms
from massspring.device import ensure_taichi
from massspring.integrators import INTEGRATORS
from massspring.kernels import proximity
from massspring.model.self_collision import mesh_edges

from conftest import FULL
from crossings import crossings, pair_distances


def sheets(resolution=10, on=True):
    scene = ms.load_scene("sheets").with_params(resolution=resolution)
    return dataclasses.replace(scene, self_collision=scene.self_collision if on else None)


def frames_crossings(sim, model, frames, steps):
    edges = mesh_edges(model.triangles)
    out = []
    for _ in range(frames):
        sim.step(steps)
        out.append(crossings(sim.positions, model.triangles, edges))
    return out


@pytest.mark.full
def test_the_counter_sees_the_sheets_pass_through_each_other_without_self_collision():
    scene = sheets(on=False)
    model = scene.model()
    sim = scene.simulation("implicit")
    counts = frames_crossings(sim, model, 6, 40)
    assert max(counts) > 20, counts


@pytest.mark.full
@pytest.mark.parametrize("integrator, resolution, dt, frames, steps", [
    ("implicit", 10, None, 6, 40), ("backward-euler", 10, None, 4, 50), ("bdf2", 10, None, 4, 50),
    ("symplectic", 8, 1e-4, 3, 1000), ("explicit", 8, 1e-4, 3, 1000), ("rk4", 8, 2e-4, 3, 500)])
def test_no_crossing_in_any_sampled_frame(integrator, resolution, dt, frames, steps):
    scene = sheets(resolution)
    model = scene.model()
    sim = scene.simulation(integrator, dt=dt)
    counts = frames_crossings(sim, model, frames, steps)
    assert counts == [0] * frames
    assert sim.self_collision_stats["repelled"] > 0  # pairs closer than the thickness: the upper sheet lies on the lower one


def shipped(name, resolution, on=True, **params):
    scene = ms.load_scene(name).with_params(resolution=resolution, **params)
    return dataclasses.replace(scene, self_collision=scene.self_collision if on else None)


@pytest.mark.full
@pytest.mark.parametrize("integrator, dt, speed", [("implicit", None, 15.0), ("symplectic", 1e-3, 100.0),
                                                   ("backward-euler", None, 15.0)])
def test_a_fast_sheet_does_not_tunnel_through_a_resting_one(integrator, dt, speed):
    """The shipped ``thrown`` scene: in its first step the upper sheet moves 1.25 (implicit,
    1/240 s at 15 m/s) or 2 (symplectic, 1 ms at 100 m/s) times the 0.05 m gap, 6 or 10
    times the thickness. Without the pass its middle ends below the lower sheet's middle;
    with it, above by at least half the thickness, and no sampled frame has a crossing."""
    n = 8 * 8
    middle = 8 * 4 + 4  # the particle nearest a sheet's centre (the upper sheet is turned about it)
    for on in (False, True):
        scene = shipped("thrown", 8, on, throw=[0.0, 0.0, -speed])
        sim = scene.simulation(integrator, dt=dt).step(1)
        gap = sim.positions[n + middle, 2] - sim.positions[middle, 2]
        if on:
            assert gap >= 0.5 * scene.self_collision.thickness
            model = scene.model()
            assert frames_crossings(sim, model, 4, 5) == [0] * 4
        else:
            assert gap < 0
        sim.close()


# (scene, resolution, integrator, frames, steps), each at the scene's default dt for it:
# test_cli's every-scene runs leave these scenes and integrators to this test
SHIPPED_RUNS = [("thrown", 10, "implicit", 4, 30), ("thrown", 8, "symplectic", 3, 1000), ("thrown", 8, "bdf2", 4, 30),
                ("ledge", 24, "implicit", 12, 60)]


@pytest.mark.fast_sample(integrator=["symplectic"])
@pytest.mark.parametrize("name, resolution, integrator, frames, steps", SHIPPED_RUNS)
def test_the_shipped_scenes_never_cross(name, resolution, integrator, frames, steps):
    """``ledge`` at its shipped size: without the pass the cloth that slid off lies on the
    ground through itself (91 crossings from 1 s on, docs/self-collision.md), with it never."""
    scene = shipped(name, resolution)
    model = scene.model()
    assert frames_crossings(scene.simulation(integrator), model, frames, steps) == [0] * frames


def slide_on_tilted_sheet(theta_deg, mu, duration=0.5, dt=1 / 240, thickness=0.01):
    """How far (m) a small sheet resting on a pinned one tilted by theta slides down it in
    ``duration`` (implicit), and its move along the normal."""
    from massspring.scene import generators

    base = dict(stiffness=1e3, damping=0.5, shear=1.0, bend=0.1, pin="none", gravity=(0.0, 0.0, -9.81))
    lower = generators.grid(resolution=10, size=1.0, mass=0.1, **base)
    upper = generators.grid(resolution=5, size=0.3, mass=0.02, **base)
    n = len(lower["positions"])
    angle = np.radians(theta_deg)
    turn = np.array([[1, 0, 0], [0, np.cos(angle), -np.sin(angle)], [0, np.sin(angle), np.cos(angle)]])
    positions = np.concatenate([lower["positions"], upper["positions"] + [0.35, 0.35, 0.75 * thickness]]) @ turn.T
    both = {key: np.concatenate([lower[key], upper[key]]) for key in ("stiffness", "damping", "rest_lengths")}
    model = ms.Model(positions, np.concatenate([lower["springs"], upper["springs"] + n]),
                     masses=np.concatenate([np.full(n, lower["masses"]), np.full(25, upper["masses"])]),
                     triangles=np.concatenate([lower["triangles"], upper["triangles"] + n]), fixed=np.arange(n),
                     self_collision=ms.SelfCollision(thickness, friction=mu), **both)
    sim = ms.Simulation(model, "implicit", dt=dt)
    start = sim.positions[n:].mean(axis=0)
    moved = sim.step(int(round(duration / dt))).positions[n:].mean(axis=0) - start
    return float(moved @ [0, -np.cos(angle), -np.sin(angle)]), float(moved @ turn[:, 2])


@pytest.mark.full
@pytest.mark.parametrize("theta, mu", [(20, 0.5), (45, 0.5), (20, 0.0)])
def test_friction_between_sheets_follows_coulomb(theta, mu):
    """A sheet on a tilted sheet sticks below tan theta = mu (creeps under 5 mm in 0.5 s)
    and above it slides as a block would: g (sin - mu cos) t^2 / 2 within 10%; it
    neither sinks into the sheet below nor leaves it (normal move under the thickness)."""
    slid, normal = slide_on_tilted_sheet(theta, mu)
    angle = np.radians(theta)
    coulomb = 0.5 * 9.81 * max(np.sin(angle) - mu * np.cos(angle), 0.0) * 0.5 ** 2
    if coulomb == 0:
        assert abs(slid) < 5e-3
    else:
        assert slid == pytest.approx(coulomb, rel=0.1)
    assert abs(normal) < 0.01


FALLING_DT = {"implicit": None, "backward-euler": None, "bdf2": None, "midpoint": None,
              "symplectic": 2e-4, "explicit": 5e-5, "rk4": 5e-4}


@pytest.mark.full
@pytest.mark.parametrize("integrator", ["backward-euler", "bdf2", "implicit", "midpoint", "symplectic"])
def test_a_cloth_that_touches_nothing_keeps_the_energy_of_its_run_without_self_collision(integrator):
    """Issue 42: the hanging cloth with a thickness a third of its spacing, no pair of
    its mesh ever within the thickness. Before, the pass held back about 400 particles a
    step of the swinging cloth (every particle's displacement was bounded, not the
    approach of its pairs): springs strained 58% and the implicit run gained 78 J
    (backward Euler 14,690 J) where the run without the pass lost 2.4 J. Now its energy
    is never above the run's without self-collision, every frame: the linearised and the
    Newton-solved steps, and symplectic Euler for the explicit ones (explicit Euler and
    RK4 meet the pass as it does, after a step into a spare state; they passed too)."""
    scene = ms.load_scene("cloth").with_params(resolution=12)
    spacing = 1.0 / 11
    thickness = spacing / 3
    dt = FALLING_DT[integrator]
    triangles = scene.model().triangles
    edges = mesh_edges(triangles)
    runs = []
    for sc in (None, ms.SelfCollision(thickness)):
        sim = dataclasses.replace(scene, self_collision=sc).simulation(integrator, dt=dt)
        steps = max(1, round(1 / 30 / sim.dt))
        energies, closest = [], np.inf
        for _ in range(15):  # half a second in frames of 1/30 s
            sim.step(steps)
            energies.append(sim.energy()["total"])
            if sc is not None:
                distances, _ = pair_distances(sim.positions, triangles, edges)
                closest = min(closest, distances.min())
        runs.append((np.array(energies), closest))
        sim.close()
    (plain, _), (guarded, closest) = runs
    assert closest > thickness  # the premise: nothing to repel
    assert np.all(guarded <= plain + 1e-9 * np.abs(plain).max()), guarded - plain


@pytest.mark.full
def test_the_pass_keeps_pairs_apart_by_at_least_half_the_thickness():
    scene = sheets()
    sim = scene.simulation("implicit")
    sim.step(200)
    stats = sim.self_collision_stats
    pairs, repelled, reach, closest = (stats[k] for k in ("pairs", "repelled", "displacement", "closest"))
    assert pairs > 0 and repelled > 0
    assert closest >= 0.5 * scene.self_collision.thickness * (1 - 1e-9)
    assert reach > 0  # the largest displacement of the step


@pytest.mark.full
def test_small_steps_skip_the_pass_only_while_no_pair_comes_within_the_thickness():
    """A step that skips the pass (every particle within its free distance of where the
    last full pass left it) may not bring a pair within the thickness, checked with the
    tests' own distances: a pair closer than that has not moved since that pass."""
    scene = sheets(8)
    model = scene.model()
    thickness = scene.self_collision.thickness
    edges = mesh_edges(model.triangles)
    sim = scene.simulation("symplectic", dt=1e-4)
    anchor, skipped, close_checked = None, 0, 0
    for step in range(3000):
        passes = sim.self_collision_stats["passes"]
        sim.step(1)
        x = sim.positions
        if sim.self_collision_stats["passes"] > passes:
            anchor = x
            continue
        skipped += 1
        if step % 20:  # the tests' distances cost about 20 ms a check
            continue
        d, particles = pair_distances(x, model.triangles, edges)
        close = d <= thickness
        moved = np.any(x[particles[close]] != anchor[particles[close]], axis=(1, 2))
        assert not moved.any(), (step, d[close][moved].min())
        close_checked += int(close.sum())
    assert 0 < sim.self_collision_stats["passes"] < skipped  # most steps skip the pass
    assert crossings(sim.positions, model.triangles, edges) == 0
    assert sim.self_collision_stats["repelled"] > 0  # the upper sheet lies on the lower one


@FULL
@pytest.mark.parametrize("height, lateral", [(0.02, (0.3, 0.25)), (0.01, (0.6, 0.45))])
def test_a_pair_within_the_thickness_is_a_penalty_of_the_implicit_solve(height, lateral):
    """One linearised implicit step of a triangle (springs on its edges) and a particle
    closer to it than the thickness, against a dense solve of Eq. 15 (tests/conftest.py)
    plus the pair's penalty assembled here: energy k (t - d)^2 / 2 on the distance d from
    the particle to the triangle's closest point q = sum b_k x_k, so dt^2 k (w w^T) (x)
    (n n^T) in A and dt k (t - d) w_k n in b, with w = (1, -b) and n = (p - q) / d. Over
    the inside (projection) and beyond an edge (closest point on it)."""
    from conftest import dense_system

    dt, k, thickness = 2e-2, 500.0, 0.05
    rng = np.random.default_rng(3)
    x = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [lateral[0], lateral[1], height]])
    x[:3] += rng.normal(scale=0.01, size=(3, 3)) * [1, 1, 0]
    model = ms.Model(x, [[0, 1], [1, 2], [2, 0]], masses=[0.01, 0.012, 0.011, 0.013], stiffness=200.0,
                     damping=0.05, velocities=rng.normal(scale=0.01, size=(4, 3)), gravity=(0, 0, 0),
                     triangles=[[0, 1, 2]], self_collision=ms.SelfCollision(thickness, stiffness=k))
    A, b = dense_system(model, dt, True)
    a_, b_, c_ = x[0], x[1], x[2]
    best = None
    for u, v in ((a_, b_), (b_, c_), (c_, a_)):  # the closest point: on an edge, or the projection inside
        q = u + np.clip(np.dot(x[3] - u, v - u) / np.dot(v - u, v - u), 0, 1) * (v - u)
        if best is None or np.linalg.norm(x[3] - q) < best[0]:
            best = (np.linalg.norm(x[3] - q), q)
    normal = np.cross(b_ - a_, c_ - a_)
    normal /= np.linalg.norm(normal)
    foot = x[3] - normal * np.dot(x[3] - a_, normal)
    bary = np.linalg.solve(np.column_stack([b_ - a_, c_ - a_, normal]), foot - a_)
    if bary[0] >= 0 and bary[1] >= 0 and bary[0] + bary[1] <= 1:
        best = (np.linalg.norm(x[3] - foot), foot)
    d, q = best
    assert d < thickness
    weights = np.linalg.lstsq(np.column_stack([a_ - c_, b_ - c_]), q - c_, rcond=None)[0]
    w = np.array([1.0, -weights[0], -weights[1], -(1 - weights.sum())])
    n = (x[3] - q) / d
    order = [3, 0, 1, 2]  # w's particles: the point, then the triangle's
    for r, pr in enumerate(order):
        for c, pc in enumerate(order):
            A[3 * pr:3 * pr + 3, 3 * pc:3 * pc + 3] += dt * dt * k * w[r] * w[c] * np.outer(n, n)
        b[3 * pr:3 * pr + 3] += dt * k * (thickness - d) * w[r] * n
    expected = np.linalg.solve(A, b).reshape(-1, 3)

    sim = ms.Simulation(model, integrator="implicit", dt=dt, cg_tol=1e-12)
    sim.step()
    assert sim.stepper.dev.sp_count.to_numpy().tolist() == [1, 0]
    assert sim.self_collision_stats["held"] == 0 and sim.self_collision_stats["left_out"] == 0  # the pass after the solve held nothing back
    np.testing.assert_allclose(sim.velocities, expected, rtol=0, atol=1e-8 * np.abs(expected).max())
    np.testing.assert_allclose(sim.positions, x + dt * sim.velocities, rtol=0, atol=1e-14)


@pytest.mark.full
def test_a_pair_list_that_grows_gives_the_bits_of_one_large_enough(monkeypatch):
    """A pass that finds more pairs than its list holds is undone and run again with a
    larger list: the run equals, to the bit, one whose list was large enough from the
    start."""
    from massspring.passes.self_collision import forward as self_collision

    monkeypatch.setattr(self_collision, "PAIR_FLOOR", 4096)  # a list the sheets outgrow
    runs = []
    for per_particle in (self_collision.PAIRS_PER_PARTICLE, 64):
        monkeypatch.setattr(self_collision, "PAIRS_PER_PARTICLE", per_particle)
        sim = sheets(16).simulation("implicit").step(100)
        runs.append((sim.positions, sim.velocities, sim.self_collision_stats["grown"],
                     sim.self_collision_stats["pairs"]))
        sim.close()
    assert runs[0][2] > 0 and runs[1][2] == 0  # the first list grew, the second did not need to
    assert runs[0][3] > 8 * 512  # more pairs than the first list held
    np.testing.assert_array_equal(runs[0][0], runs[1][0])
    np.testing.assert_array_equal(runs[0][1], runs[1][1])


@pytest.mark.full
def test_a_pair_list_that_cannot_grow_is_an_error_naming_it_and_the_simulation_keeps_its_list(monkeypatch):
    """Issue 42: a pair list that could not grow raised a ValueError naming "0 particles
    and 0 springs" and left the Simulation without a list."""
    from massspring import device
    from massspring.support import memory
    from massspring.passes.self_collision import forward as self_collision

    monkeypatch.setattr(self_collision, "PAIR_FLOOR", 4096)  # a list the sheets outgrow
    sim = sheets(16).simulation("implicit")
    capacity = sim.passes[0].capacity
    monkeypatch.setattr(device.POOL, "take", lambda signature: None)  # no pooled list of the next size
    monkeypatch.setattr(memory, "available", lambda: (1e4, "available"))
    with pytest.raises(memory.MemoryNeedError, match=r"^self-collision: a pair list of [\d,]+ pairs \([\d,]+ within "
                                                     r"reach\) needs about .* GB; 1e-05 GB available"):
        sim.step(100)  # the list of 8 pairs a particle grows within 100 steps
    assert sim.passes[0].capacity == capacity and sim.self_collision_stats["grown"] == 0
    assert np.isfinite(sim.positions).all()
    sim.close()


@pytest.mark.full
def test_a_run_gives_the_same_bits_before_and_after_other_simulations_in_its_process():
    """Issue 42: a result must not depend on the simulations that ran before it in the same
    process: pooled fields keep the values of other models (larger and smaller ones of the
    same capacity class, other integrators, a pair list that grew), and kernels compiled
    for them are reused."""
    def case():
        sim = sheets(8).simulation("implicit")
        sim.step(40)
        out = sim.positions, sim.velocities, sim.self_collision_stats["pairs"]
        sim.close()
        return out

    first = case()
    for scene, integrator in ((sheets(12), "implicit"), (sheets(6), "symplectic"), (sheets(10), "backward-euler"),
                              (ms.load_scene("cloth").with_params(resolution=20), "implicit")):
        sim = scene.simulation(integrator)
        sim.step(30)
        sim.close()
    again = case()
    assert first[2] > 0
    np.testing.assert_array_equal(first[0], again[0])
    np.testing.assert_array_equal(first[1], again[1])
    assert first[2] == again[2]


@pytest.mark.full
def test_one_and_two_threads_give_the_same_bits():
    script = ("import hashlib, massspring as ms\n"
              "sim = ms.load_scene('sheets').with_params(resolution=10).simulation(loops='parallel')\n"
              "sim.step(120)\n"
              "print(hashlib.sha256(sim.positions.tobytes() + sim.velocities.tobytes()).hexdigest())\n")
    out = []
    for threads in ("1", "2"):
        env = dict(os.environ, TI_CPU_MAX_NUM_THREADS=threads)
        proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=300)
        assert proc.returncode == 0, proc.stderr
        out.append(proc.stdout.split()[-1])
    assert out[0] == out[1]


@FULL
def test_restart_continues_to_the_bit():
    scene = sheets()
    runs = []
    for steps in (100, 60):  # one run after the other: they share one bundle (kernels compiled once)
        sim = scene.simulation("implicit").step(steps)
        runs.append((sim.positions, sim.velocities, sim.carried_state()))
        sim.close()
    x, v, carried = runs[1]
    second = scene.simulation("implicit").set_state(x, v, steps=60, carried=carried).step(40)
    np.testing.assert_array_equal(runs[0][0], second.positions)
    np.testing.assert_array_equal(runs[0][1], second.velocities)


@FULL
def test_a_restart_between_skipped_passes_continues_to_the_bit():
    scene = sheets(8)
    runs = []
    for steps in (1500, 1000):
        sim = scene.simulation("symplectic", dt=1e-4).step(steps)
        runs.append((sim.positions, sim.velocities, sim.carried_state(), sim.self_collision_stats["passes"]))
        sim.close()
    x, v, carried = runs[1][:3]
    assert set(carried) == {"sc_anchor", "sc_free"} and runs[1][3] < 500
    second = scene.simulation("symplectic", dt=1e-4).set_state(x, v, steps=1000, carried=carried).step(500)
    np.testing.assert_array_equal(runs[0][0], second.positions)
    np.testing.assert_array_equal(runs[0][1], second.velocities)


@pytest.mark.full
def test_tablecloth_as_shipped_keeps_self_collision_and_a_sampled_start_has_no_crossing():
    scene = ms.load_scene("tablecloth")
    assert scene.self_collision is not None
    scene = scene.with_params(resolution=16)
    model = scene.model()
    sim = scene.simulation()
    assert frames_crossings(sim, model, 1, 60) == [0]


# ---------------------------------------------------------------- the narrow phase


@ti.func
def _point(p: ti.template(), k, m):
    """Point m (columns 3 m .. 3 m + 2) of row k."""
    return ti.Vector([p[k, 3 * m], p[k, 3 * m + 1], p[k, 3 * m + 2]])


@ti.kernel
def _point_triangle(p: ti.types.ndarray(dtype=ti.f64, ndim=2), out: ti.types.ndarray(dtype=ti.f64, ndim=2)):
    for k in range(p.shape[0]):
        d, w = proximity.point_triangle(_point(p, k, 0), _point(p, k, 1), _point(p, k, 2), _point(p, k, 3))
        out[k, 0] = d
        for m in ti.static(range(3)):
            out[k, 1 + m] = w[m]


@ti.kernel
def _segment_segment(p: ti.types.ndarray(dtype=ti.f64, ndim=2), out: ti.types.ndarray(dtype=ti.f64, ndim=2)):
    for k in range(p.shape[0]):
        d, s, t = proximity.segment_segment(_point(p, k, 0), _point(p, k, 1), _point(p, k, 2), _point(p, k, 3))
        out[k, 0] = d
        out[k, 1] = s
        out[k, 2] = t


def _sampled_triangle_distance(p, a, b, c, n=120):
    u, v = np.meshgrid(np.linspace(0, 1, n + 1), np.linspace(0, 1, n + 1))
    keep = u + v <= 1
    points = a + u[keep][:, None] * (b - a) + v[keep][:, None] * (c - a)
    return np.linalg.norm(points - p, axis=1).min()


def _sampled_segment_distance(p1, q1, p2, q2, n=400):
    s = np.linspace(0, 1, n + 1)
    first = p1 + s[:, None] * (q1 - p1)
    second = p2 + s[:, None] * (q2 - p2)
    return np.linalg.norm(first[:, None, :] - second[None, :, :], axis=2).min()


TRIANGLE_CASES = {
    "above the interior": ([0.2, 0.2, 0.5], [0, 0, 0], [1, 0, 0], [0, 1, 0]),
    "beyond a vertex": ([2.0, -1.0, 0.3], [0, 0, 0], [1, 0, 0], [0, 1, 0]),
    "beyond an edge": ([0.8, 0.8, -0.2], [0, 0, 0], [1, 0, 0], [0, 1, 0]),
    "in the plane, inside": ([0.25, 0.25, 0.0], [0, 0, 0], [1, 0, 0], [0, 1, 0]),
    "on a vertex": ([1.0, 0.0, 0.0], [0, 0, 0], [1, 0, 0], [0, 1, 0]),
    "degenerate (collinear)": ([0.5, 1.0, 0.0], [0, 0, 0], [1, 0, 0], [2, 0, 0]),
    "degenerate (a point)": ([0.3, 0.4, 0.0], [1, 1, 1], [1, 1, 1], [1, 1, 1]),
}

SEGMENT_CASES = {
    "crossing at a distance": ([0, 0, 0], [1, 0, 0], [0.5, -1, 0.3], [0.5, 1, 0.3]),
    "parallel, overlapping": ([0, 0, 0], [1, 0, 0], [0.5, 0.2, 0], [1.5, 0.2, 0]),
    "parallel, apart": ([0, 0, 0], [1, 0, 0], [2, 0.1, 0], [3, 0.1, 0]),
    "collinear": ([0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]),
    "coincident points": ([0.5, 0.5, 0.5], [0.5, 0.5, 0.5], [0.5, 0.5, 0.5], [0.5, 0.5, 0.5]),
    "a point and a segment": ([0.3, 1, 0], [0.3, 1, 0], [0, 0, 0], [1, 0, 0]),
    "touching": ([0, 0, 0], [1, 0, 0], [0.5, 0, 0], [0.5, 1, 0]),
}


@pytest.mark.parametrize("case", list(TRIANGLE_CASES))
def test_point_triangle_distance_against_sampling(case):
    ensure_taichi()
    data = np.array([np.concatenate([np.asarray(v, float) for v in TRIANGLE_CASES[case]])])
    out = np.zeros((1, 4))
    _point_triangle(data, out)
    p, a, b, c = (data[0, 3 * k:3 * k + 3] for k in range(4))
    d, w = out[0, 0], out[0, 1:]
    assert np.all(w >= -1e-12) and abs(w.sum() - 1) < 1e-12
    assert d == pytest.approx(np.linalg.norm(p - (w[0] * a + w[1] * b + w[2] * c)), abs=1e-12)
    sampled = _sampled_triangle_distance(p, a, b, c)
    assert d <= sampled + 1e-12 and d >= sampled - 2e-2 * max(1.0, np.linalg.norm(b - a))


@pytest.mark.parametrize("case", list(SEGMENT_CASES))
def test_segment_segment_distance_against_sampling(case):
    ensure_taichi()
    data = np.array([np.concatenate([np.asarray(v, float) for v in SEGMENT_CASES[case]])])
    out = np.zeros((1, 3))
    _segment_segment(data, out)
    p1, q1, p2, q2 = (data[0, 3 * k:3 * k + 3] for k in range(4))
    d, s, t = out[0]
    assert 0 <= s <= 1 and 0 <= t <= 1
    assert d == pytest.approx(np.linalg.norm((p1 + s * (q1 - p1)) - (p2 + t * (q2 - p2))), abs=1e-12)
    sampled = _sampled_segment_distance(p1, q1, p2, q2)
    assert d <= sampled + 1e-12 and d >= sampled - 1e-2


# ---------------------------------------------------------------- data and compilation


@pytest.mark.parametrize("fields, message", [({"thickness": 0}, "thickness: must be > 0"),
                                             ({"thickness": "a"}, "thickness"),
                                             ({"thickness": 0.01, "friction": -1}, "friction: must be >= 0"),
                                             ({"thickness": 0.01, "stiffness": 0}, "stiffness: must be > 0"),
                                             ({"thickness": float("nan")}, "thickness")])
def test_bad_fields_are_refused_by_name(fields, message):
    with pytest.raises(ValueError, match=message):
        ms.SelfCollision(**fields)


def test_a_model_needs_triangles_and_a_self_collision_object():
    with pytest.raises(ValueError, match="self_collision: needs the model's triangles"):
        ms.Model([[0, 0, 0], [1, 0, 0]], [[0, 1]], self_collision=ms.SelfCollision(0.01))
    with pytest.raises(ValueError, match="self_collision: expected a massspring.SelfCollision"):
        ms.Model([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1]], triangles=[[0, 1, 2]], self_collision=0.01)


def test_scene_table_errors_name_the_key(tmp_path):
    base = 'integrator = "implicit"\nduration = 1.0\n[model]\ngenerator = "grid"\nresolution = 4\n'
    for table, message in (("[self_collision]\nthick = 0.1\n", "self_collision.thick: unknown key"),
                           ("[self_collision]\nfriction = 0.1\n", "self_collision.thickness: missing"),
                           ("[self_collision]\nthickness = -1.0\n", "self_collision.thickness: must be > 0")):
        path = tmp_path / "s.toml"
        path.write_text(base + table)
        with pytest.raises(ms.SceneError, match=message):
            ms.load_scene(str(path))


def test_default_stiffness_is_the_median_spring_stiffness():
    model = sheets().model()
    assert model.self_collision.repulsion_stiffness(model) == np.median(model.stiffness[model.stiffness > 0])


def test_nothing_is_compiled_or_allocated_without_it():
    on = sheets().simulation().info()
    off = sheets(on=False).simulation().info()
    assert "self-collision" in on["terms"] and "self-collision" not in off["terms"]
    assert any(name.startswith("sc_") for name in on["arrays"])
    assert not any(name.startswith("sc_") for name in off["arrays"])


def test_stacked_layers_are_counted_before_they_are_built():
    scene = ms.load_scene("sheets")
    model = scene.model()
    assert scene.counts() == (model.n_particles, model.n_springs)
    assert model.n_particles == 2 * scene.params["resolution"] ** 2
    assert model.fingerprint() != dataclasses.replace(scene, self_collision=None).model().fingerprint()


@pytest.mark.parametrize("throw, message", [([0, 0], "expected 3 numbers"), ([0, 0, float("inf")], "finite")])
def test_a_bad_throw_is_refused_by_name(throw, message):
    with pytest.raises(ms.SceneError, match=f"model.throw: .*{message}"):
        ms.load_scene("thrown").with_params(throw=throw).model()


def test_throw_moves_the_upper_sheets_only():
    model = ms.load_scene("thrown").with_params(resolution=4, layers=3).model()
    v = model.velocities
    assert np.all(v[:16] == 0) and np.all(v[16:] == [0.0, 0.0, -15.0])


def test_the_spacing_of_a_grid_is_the_height_of_its_triangles():
    """``mesh_spacing`` of a grid of spacing h (right triangles of legs h): h / sqrt(2),
    the distance from a corner to the triangle across its diagonal."""
    from massspring.model.self_collision import mesh_spacing

    model = ms.load_scene("cloth").with_params(resolution=11).model()
    assert mesh_spacing(model.positions, model.triangles) == pytest.approx(0.1 / np.sqrt(2), rel=1e-12)
    assert mesh_spacing(model.positions, np.zeros((0, 3), dtype=int)) == 0


def test_a_thickness_above_half_the_mesh_spacing_is_refused_before_anything_runs():
    """Issue 42: a 225 x 225 grid (4.5 mm apart) with thickness 5 mm listed 20.6 million
    pairs in its first step (32 s). Now the model is refused as it is built, naming the
    thickness and the spacing (3.18 mm, the triangles' height); half the spacing is
    accepted."""
    scene = ms.load_scene("cloth").with_params(resolution=225)
    spacing = 1.0 / 224 / np.sqrt(2)
    with pytest.raises(ValueError, match=r"self_collision: thickness 0.005 m is more than half the mesh's spacing "
                                         r"0.00316 m .* at most 0.00158 m"):
        dataclasses.replace(scene, self_collision=ms.SelfCollision(0.005)).model()
    model = dataclasses.replace(scene, self_collision=ms.SelfCollision(0.49 * spacing)).model()
    assert model.self_collision.thickness == 0.49 * spacing


def test_a_too_thick_scene_is_one_line_at_the_command_line(tmp_path, capsys):
    """The same refusal from a scene file: exit 2, one line naming the thickness."""
    from conftest import one_line_error
    from massspring.cli import main

    path = tmp_path / "thick.toml"
    path.write_text('integrator = "implicit"\nduration = 1.0\n\n[model]\ngenerator = "grid"\nresolution = 20\nsize = 1.0\n\n[self_collision]\nthickness = 0.03\n')
    assert main(["run", str(path), "--steps", "1", "--quiet"]) == 2
    one_line_error(capsys, "thickness 0.03 m is more than half the mesh's spacing")


@FULL
@pytest.mark.parametrize("integrator", [name for name, cls in INTEGRATORS.items() if cls.traits.newton])
def test_a_newton_solved_step_starts_from_the_velocities_the_pass_left(integrator):
    """The pass changes velocities after a step; a Newton-solved step takes its v_n from
    what the last step committed, so the pass's change must reach it: a run continued
    from its state (set_state, which starts afresh from the velocities given) equals the
    unbroken run to the bit, over steps in which the pass repelled pairs."""
    scene = sheets(6)
    whole = scene.simulation(integrator).step(70)  # the upper sheet lands at step 45 or so
    part = scene.simulation(integrator).step(55)
    x, v, carried = part.positions, part.velocities, part.carried_state()
    assert part.self_collision_stats["repelled"] > 0
    part.close()
    rest = scene.simulation(integrator).set_state(x, v, steps=55, carried=carried).step(15)
    assert whole.self_collision_stats["repelled"] > 0
    np.testing.assert_array_equal(rest.positions, whole.positions)
    np.testing.assert_array_equal(rest.velocities, whole.velocities)
    whole.close()
    rest.close()
