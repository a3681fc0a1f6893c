"""Input validation of Model and Simulation, and the Model's derived data.

Every bad input must raise ``ValueError`` whose message starts with the name of
the offending argument, before any kernel is compiled or launched.
"""

import math

import numpy as np
import pytest

import massspring as ms
from massspring.device import adjacency

POS = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]
SPRINGS = [[0, 1], [1, 2]]


def model(**kw):
    args = dict(positions=POS, springs=SPRINGS)
    args.update(kw)
    return ms.Model(**args)


def raises_naming(name, fn, *args, **kw):
    """``fn`` raises ValueError and the message names argument ``name``."""
    with pytest.raises(ValueError) as info:
        fn(*args, **kw)
    msg = str(info.value)
    assert msg.startswith(name + ":"), f"message does not name {name!r}: {msg!r}"
    return msg


# ----------------------------------------------------------------------------- Model


@pytest.mark.parametrize("springs", [[[0, 3]], [[0, 1], [-1, 2]], [[7, 1]], [[0, 1.5]]],
                         ids=["past-end", "negative", "far", "non-integer"])
def test_spring_index_invalid(springs):
    raises_naming("springs", model, springs=springs)


def test_spring_self_loop():
    msg = raises_naming("springs", model, springs=[[0, 1], [2, 2]])
    assert "itself" in msg


@pytest.mark.parametrize("masses", [0.0, -1.0, [1.0, 0.0, 1.0], [1.0, -2.0, 1.0], math.nan, math.inf,
                                    [1.0, math.nan, 1.0], [1.0, 1.0, -math.inf]])
def test_bad_masses(masses):
    raises_naming("masses", model, masses=masses)


@pytest.mark.parametrize("name", ["stiffness", "damping", "rest_lengths"])
@pytest.mark.parametrize("value", [-1.0, [1.0, -0.5], math.nan, [1.0, math.inf]],
                         ids=["neg-scalar", "neg-item", "nan", "inf"])
def test_bad_spring_parameters(name, value):
    raises_naming(name, model, **{name: value})


@pytest.mark.parametrize("name", ["stiffness", "damping", "rest_lengths"])
def test_spring_parameters_wrong_length(name):
    raises_naming(name, model, **{name: [1.0, 1.0, 1.0]})


def test_zero_stiffness_damping_rest_length_allowed():
    m = model(stiffness=0.0, damping=0.0, rest_lengths=0.0)
    assert np.all(m.stiffness == 0) and np.all(m.damping == 0) and np.all(m.rest_lengths == 0)


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_positions(bad):
    pos = np.array(POS)
    pos[1, 2] = bad
    raises_naming("positions", model, positions=pos)


@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_non_finite_velocities(bad):
    vel = np.zeros((3, 3))
    vel[2, 0] = bad
    raises_naming("velocities", model, velocities=vel)


@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_non_finite_gravity(bad):
    raises_naming("gravity", model, gravity=(0.0, bad, -9.81))


@pytest.mark.parametrize("positions", [np.zeros((3, 2)), np.zeros((3, 4)), np.zeros(9), np.zeros((0, 3)),
                                       np.zeros((3, 3, 1))])
def test_positions_wrong_shape(positions):
    raises_naming("positions", model, positions=positions)


@pytest.mark.parametrize("springs", [[[0, 1, 2]], [0, 1], [[[0, 1]]]])
def test_springs_wrong_shape(springs):
    raises_naming("springs", model, springs=springs)


@pytest.mark.parametrize("masses", [[1.0, 1.0], [1.0, 1.0, 1.0, 1.0], [[1.0, 1.0, 1.0]]])
def test_masses_wrong_length(masses):
    raises_naming("masses", model, masses=masses)


@pytest.mark.parametrize("velocities", [np.zeros((2, 3)), np.zeros((3, 2)), np.zeros(9)])
def test_velocities_wrong_shape(velocities):
    raises_naming("velocities", model, velocities=velocities)


@pytest.mark.parametrize("gravity", [(0.0, -9.81), (0.0, 0.0, -9.81, 0.0), [[0.0, 0.0, -9.81]]])
def test_gravity_wrong_shape(gravity):
    raises_naming("gravity", model, gravity=gravity)


@pytest.mark.parametrize("fixed", [[3], [-1], [0.5], np.array([True, False])])
def test_bad_fixed(fixed):
    raises_naming("fixed", model, fixed=fixed)


@pytest.mark.parametrize("fixed", [[1], np.array([False, True, False]), 1])
def test_fixed_velocity_set_to_zero(fixed):
    vel = np.arange(9.0).reshape(3, 3) + 1.0
    m = model(velocities=vel, fixed=fixed)
    np.testing.assert_array_equal(m.fixed, [1])
    np.testing.assert_array_equal(m.velocities[1], 0.0)
    np.testing.assert_array_equal(m.velocities[[0, 2]], vel[[0, 2]])
    np.testing.assert_array_equal(m.free_mask(), [True, False, True])


def test_fixed_sorted_unique():
    m = model(fixed=[2, 0, 2])
    np.testing.assert_array_equal(m.fixed, [0, 2])


def test_rest_lengths_default_to_initial_distances():
    rng = np.random.default_rng(1)
    pos = rng.normal(size=(6, 3))
    springs = np.array([[0, 1], [2, 5], [3, 4], [5, 0], [1, 3]])
    m = ms.Model(pos, springs)
    expected = [math.dist(pos[i], pos[j]) for i, j in springs]
    np.testing.assert_allclose(m.rest_lengths, expected, rtol=1e-15)
    # a scalar is broadcast to every spring
    np.testing.assert_array_equal(ms.Model(pos, springs, rest_lengths=0.25).rest_lengths, 0.25)


def test_scalar_parameters_broadcast():
    m = model(masses=2.0, stiffness=3.0, damping=0.5)
    np.testing.assert_array_equal(m.masses, [2.0, 2.0, 2.0])
    np.testing.assert_array_equal(m.stiffness, [3.0, 3.0])
    np.testing.assert_array_equal(m.damping, [0.5, 0.5])
    assert m.n_particles == 3 and m.n_springs == 2


def brute_force_adjacency(n, springs):
    """For each particle, the (spring, other end) pairs of the springs touching it."""
    rows = [[] for _ in range(n)]
    for s, (i, j) in enumerate(springs):
        rows[i].append((s, j))
        rows[j].append((s, i))
    return rows


@pytest.mark.parametrize("seed", range(4))
def test_adjacency_csr(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 12))
    m_springs = int(rng.integers(0, 25))
    springs = []
    while len(springs) < m_springs:  # duplicates allowed (parallel springs), no self loops
        i, j = rng.integers(0, n, 2)
        if i != j:
            springs.append([int(i), int(j)])
    if n > 2:  # leave the last particle without springs
        springs = [s for s in springs if n - 1 not in s]
    m = ms.Model(rng.normal(size=(n, 3)), np.array(springs, dtype=np.int64).reshape(-1, 2))
    offsets, other, entry = adjacency(m)
    assert offsets.shape == (n + 1,) and other.shape == (2 * m.n_springs,) and entry.shape == other.shape
    # entry: s where the particle is the spring's first end, -1 - s where it is the second
    spring = np.where(entry >= 0, entry, -1 - entry)
    owner = np.repeat(np.arange(n), np.diff(offsets))
    first = entry >= 0
    np.testing.assert_array_equal(m.springs[spring[first], 0], owner[first])
    np.testing.assert_array_equal(m.springs[spring[~first], 1], owner[~first])
    assert offsets[0] == 0 and offsets[-1] == 2 * m.n_springs
    assert np.all(np.diff(offsets) >= 0)
    expected = brute_force_adjacency(n, m.springs.tolist())
    for i in range(n):
        row = list(zip(spring[offsets[i]:offsets[i + 1]].tolist(), other[offsets[i]:offsets[i + 1]].tolist()))
        assert sorted(row) == sorted(expected[i]), f"particle {i}"
    # every spring listed exactly twice, once from each end
    np.testing.assert_array_equal(np.bincount(spring, minlength=m.n_springs), 2)


def test_model_arrays_read_only_copies():
    pos = np.array(POS)
    vel = np.ones((3, 3))
    m = model(positions=pos, velocities=vel, masses=[1.0, 2.0, 3.0])
    for name in ("positions", "springs", "masses", "stiffness", "damping", "rest_lengths",
                 "velocities", "gravity", "fixed", "triangles"):
        arr = getattr(m, name)
        assert not arr.flags.writeable, name
        with pytest.raises(ValueError):
            arr[...] = 0
    pos[0, 0] = 5.0  # the model holds copies
    vel[0, 0] = 5.0
    assert m.positions[0, 0] == 0.0 and m.velocities[0, 0] == 1.0
    with pytest.raises(Exception):
        m.positions = np.zeros((3, 3))


# ----------------------------------------------------------------------------- Simulation


def test_simulation_rejects_non_model():
    raises_naming("model", ms.Simulation, {"positions": POS})


@pytest.mark.parametrize("dt", [0.0, -1e-3, math.nan, math.inf, "abc", None])
def test_simulation_bad_dt(dt):
    raises_naming("dt", ms.Simulation, model(), dt=dt)


@pytest.mark.fast_sample(integrator=["rk2"])
@pytest.mark.parametrize("integrator", ["rk2", "Implicit", "", None])
def test_simulation_bad_integrator(integrator):
    raises_naming("integrator", ms.Simulation, model(), integrator=integrator)


@pytest.mark.parametrize("precision", ["f16", "float64", 64, None])
def test_simulation_bad_precision(precision):
    raises_naming("precision", ms.Simulation, model(), precision=precision)


@pytest.mark.parametrize("cg_tol", [0.0, -1e-6, 1.0, 2.0, math.nan, math.inf, "tight"])
def test_simulation_bad_cg_tol(cg_tol):
    raises_naming("cg_tol", ms.Simulation, model(), cg_tol=cg_tol)


@pytest.mark.parametrize("cg_max_iter", [0, -5, 2.5, True, "10", 1e3])
def test_simulation_bad_cg_max_iter(cg_max_iter):
    raises_naming("cg_max_iter", ms.Simulation, model(), cg_max_iter=cg_max_iter)


def test_simulation_bad_preconditioner():
    raises_naming("preconditioner", ms.Simulation, model(), preconditioner="ilu")


def test_simulation_bad_arch():
    raises_naming("arch", ms.Simulation, model(), arch="quantum")
    # Taichi is now (or already) running on the CPU; asking for another arch is refused too
    ms.Simulation(model(), integrator="explicit")
    raises_naming("arch", ms.Simulation, model(), integrator="explicit", arch="cuda")


def test_simulation_defaults_and_counters():
    sim = ms.Simulation(model(fixed=[0]), integrator="explicit", dt=0.01)
    assert sim.steps == 0 and sim.time == 0.0 and sim.solver_stats is None and sim.cg_iterations == []
    sim.step(3)
    assert sim.steps == 3 and sim.time == pytest.approx(0.03)
    assert sim.positions.dtype == np.float64 and sim.velocities.shape == (3, 3)
    with pytest.raises(ValueError):
        sim.step(-1)


def test_energy_of_known_state():
    m = ms.Model([[0.0, 0.0, 1.0], [2.0, 0.0, 0.0]], [[0, 1]], masses=[1.0, 3.0], stiffness=10.0,
                 rest_lengths=1.5, velocities=[[1.0, 0.0, 0.0], [0.0, 2.0, 0.0]], gravity=(0.0, 0.0, -10.0))
    e = m.energy(m.positions, m.velocities)
    assert e["kinetic"] == pytest.approx(0.5 * (1.0 * 1.0 + 3.0 * 4.0))
    assert e["spring"] == pytest.approx(0.5 * 10.0 * (math.sqrt(5.0) - 1.5) ** 2)
    assert e["gravity"] == pytest.approx(10.0)  # -sum m g.x = -(1 * -10 * 1)
    assert e["total"] == pytest.approx(e["kinetic"] + e["spring"] + e["gravity"])
    sim = ms.Simulation(m, integrator="explicit")
    assert sim.energy() == pytest.approx(e)


def test_info_lists_only_what_the_run_needs():
    plain = model(damping=0.0, gravity=(0.0, 0.0, 0.0))
    info = ms.Simulation(plain, integrator="explicit").info()
    assert info["terms"] == ["spring"]
    spring_arrays = {"x", "v", "mass", "ends", "offsets", "other", "entry", "fs", "ks", "l0"}
    assert set(info["arrays"]) == spring_arrays | {"x_spare", "v_spare"}
    assert info["particles"] == 3 and info["springs"] == 2 and info["bytes"] > 0
    full = model(damping=0.5, fixed=[0])
    info = ms.Simulation(full, integrator="implicit").info()
    assert info["terms"] == ["spring", "damping", "gravity", "fixed-filter"]
    cg = {"b", "r", "z", "p", "q", "keep", "diag", "coef", "spring_coef"}
    assert set(info["arrays"]) == spring_arrays | {"free", "kd", "gravity", "minv"} | cg
    info = ms.Simulation(full, integrator="implicit", preconditioner="none").info()
    assert "minv" not in info["arrays"]
    bare = ms.Model([[0.0, 0.0, 0.0]], [], gravity=(0.0, 0.0, 0.0))
    assert set(ms.Simulation(bare, integrator="symplectic").info()["arrays"]) == {
        "x", "v", "mass", "x_spare", "v_spare"}


def test_triangles_validated():
    assert model().triangles.shape == (0, 3)
    assert model(triangles=[[0, 1, 2]]).triangles.tolist() == [[0, 1, 2]]
    for bad in ([[0, 1]], [[0, 1, 3]], [[0, 1, 1]], [[0.0, 1.0, 2.0]], [[-1, 0, 1]]):
        raises_naming("triangles", model, triangles=bad)


def test_fingerprint_tells_models_apart_by_their_physics():
    x = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]
    a = ms.Model(x, [[0, 1], [1, 2]], stiffness=[10.0, 20.0])
    assert a.fingerprint() == ms.Model(x, [[0, 1], [1, 2]], stiffness=[10.0, 20.0]).fingerprint()
    assert a.fingerprint() == ms.Model(x, [[0, 1], [1, 2]], stiffness=[10.0, 20.0], triangles=[[0, 1, 2]]).fingerprint()
    for changed in (dict(stiffness=[10.0, 20.000000000000004]), dict(stiffness=[10.0, 20.0], fixed=[0]),
                    dict(stiffness=[10.0, 20.0], rest_lengths=1.0), dict(stiffness=[10.0, 20.0], masses=2.0)):
        assert ms.Model(x, [[0, 1], [1, 2]], **changed).fingerprint() != a.fingerprint(), changed
    assert set(a.fingerprint()) <= set("0123456789abcdef") and len(a.fingerprint()) == 64  # SHA-256, hex
