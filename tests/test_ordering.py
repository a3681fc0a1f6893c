"""The cache-friendly renumbering (``massspring.model.ordering``): when it applies, what the
renumbered copy holds, and that a Simulation stepping it is the user's model to
round-off (explicit) or to tolerance (implicit, against a dense solve of Eq. 15),
with every array at the API in the user's order."""

import json

import numpy as np
import pytest

import massspring as ms
from conftest import FULL, dense_step
from massspring.model import ordering
from massspring.cli import main
from massspring.io.obj import read_obj, write_obj


def scrambled(model, seed):
    """``model`` with its particles and springs in a random order: its particle k is
    ``model``'s particle ``perm[k]``. Returns (scrambled model, perm)."""
    rng = np.random.default_rng(seed)
    perm = rng.permutation(model.n_particles)
    return ordering.renumbered(model, perm, rng.permutation(model.n_springs)), perm


def cloth(resolution, **changes):
    base = ms.load_scene("cloth").with_params(resolution=resolution).model()
    args = dict(masses=base.masses, stiffness=base.stiffness, damping=base.damping, rest_lengths=base.rest_lengths,
                gravity=base.gravity, fixed=base.fixed, triangles=base.triangles)
    args.update(changes)
    return ms.Model(base.positions, base.springs, **args)


@pytest.fixture
def small_window(monkeypatch):
    """A window of 4 particles, so that small scrambled models are renumbered."""
    monkeypatch.setattr(ordering, "WINDOW", 4)


def test_far_share_counts_far_ends_and_far_steps():
    springs = np.array([[0, 1], [0, 9], [20, 21], [21, 2]])
    # ends more than 5 apart: (0, 9), (21, 2); steps of the first end: 0 -> 0, 0 -> 20, 20 -> 21
    assert ordering.far_share(springs, 5) == pytest.approx(3 / 8)
    assert ordering.far_share(springs, 100) == 0.0
    assert ordering.far_share(np.zeros((0, 2), dtype=np.int64), 5) == 0.0


def test_morton_order_walks_the_cube_corners_x_fastest():
    corners = np.array([(x, y, z) for z in (0, 1) for y in (0, 1) for x in (0, 1)], dtype=float)
    shuffle = np.array([5, 2, 7, 0, 3, 6, 1, 4])
    order = ordering.morton_order(corners[shuffle])
    assert np.array_equal(shuffle[order], np.arange(8))
    # Z-order keeps a cell's 2x2x2 block together before moving on
    lattice = np.array([(x, y, z) for x in range(4) for y in range(4) for z in range(4)], dtype=float)
    first = lattice[ordering.morton_order(lattice)[:8]]
    assert first.max() == 1.0 and len(np.unique(first, axis=0)) == 8


def test_well_ordered_models_are_stepped_as_given():
    model = cloth(100)
    assert ordering.plan(model) is None
    sim = ms.Simulation(model, integrator="symplectic", dt=1e-5)
    assert sim.info()["order"] == "given"
    sim.close()


def test_the_renumbered_copy_is_the_same_system():
    pins = ms.load_scene("cloth").with_params(resolution=100).model().fixed.size
    model, _ = scrambled(cloth(100, pin_velocity=0.01 * np.arange(3 * pins).reshape(pins, 3)), 0)
    assert ordering.far_share(model.springs, ordering.WINDOW) > ordering.FAR_SHARE
    plan = ordering.plan(model)
    assert plan is not None
    inner = plan.model
    assert np.array_equal(np.sort(plan.particles), np.arange(model.n_particles))
    assert np.array_equal(plan.particles[plan.inverse], np.arange(model.n_particles))
    assert ordering.far_share(inner.springs, ordering.WINDOW) < 0.5 * ordering.far_share(model.springs, ordering.WINDOW)
    # spring k of the copy is spring springs[k] of the model, between the same particles
    assert np.array_equal(plan.particles[inner.springs], model.springs[plan.springs])
    for name in ("stiffness", "damping", "rest_lengths"):
        assert np.array_equal(getattr(inner, name), getattr(model, name)[plan.springs])
    for name in ("positions", "velocities", "masses"):
        assert np.array_equal(getattr(inner, name), getattr(model, name)[plan.particles])
    user_pins = plan.particles[inner.fixed]
    assert np.array_equal(np.sort(user_pins), model.fixed)
    assert np.array_equal(inner.pin_velocity, model.pin_velocity[np.searchsorted(model.fixed, user_pins)])
    assert np.array_equal(plan.particles[inner.triangles], model.triangles)
    assert np.array_equal(plan.to_user(plan.to_inner(model.positions)), model.positions)
    assert ordering.plan(model) is plan  # made once per model


@pytest.mark.parametrize("loops", ["serial", "parallel"])
def test_a_scrambled_cloth_steps_as_the_grid_does(loops):
    grid = cloth(100)
    model, perm = scrambled(grid, 1)
    a = ms.Simulation(grid, integrator="symplectic", dt=2e-6, loops=loops).step(100)
    b = ms.Simulation(model, integrator="symplectic", dt=2e-6, loops=loops).step(100)
    assert (a.info()["order"], b.info()["order"]) == ("given", "z-order")
    moved = np.abs(a.positions - grid.positions).max()
    assert moved > 1e-8
    # the same sums in another order: round-off of the displacement
    assert np.abs(b.positions - a.positions[perm]).max() <= 1e-12 * moved
    assert np.abs(b.velocities - a.velocities[perm]).max() <= 1e-12 * np.abs(a.velocities).max()
    pinned = model.fixed
    assert np.array_equal(b.positions[pinned], model.positions[pinned])
    a.close()
    b.close()


@pytest.mark.fast_sample(preconditioner=["block-jacobi"])
@pytest.mark.parametrize("preconditioner", ["block-jacobi", "multigrid"])
def test_a_renumbered_implicit_step_is_the_dense_solve_of_eq15(small_window, preconditioner):
    model, _ = scrambled(cloth(12), 2)
    sim = ms.Simulation(model, integrator="implicit", dt=1 / 60, cg_tol=1e-10, preconditioner=preconditioner)
    assert sim.info()["order"] == "z-order"
    sim.step(1)
    v = dense_step(model, 1 / 60, True)
    assert np.abs(sim.velocities - v).max() <= 1e-7 * np.abs(v).max()
    assert np.allclose(sim.positions, model.positions + v / 60, rtol=0, atol=1e-12)
    sim.close()


@FULL
@pytest.mark.parametrize("integrator", ["symplectic", "implicit"])
def test_a_renumbered_run_with_self_collision_is_the_users(small_window, integrator):
    grid = cloth(16, self_collision=ms.SelfCollision(0.02))
    model, perm = scrambled(grid, 4)
    dt, steps, tol = (2e-4, 50, 1e-12) if integrator == "symplectic" else (1 / 60, 4, 1e-6)
    a = ms.Simulation(grid, integrator=integrator, dt=dt).step(steps)
    b = ms.Simulation(model, integrator=integrator, dt=dt).step(steps)
    assert b.info()["order"] == "z-order" and b.self_collision_stats["pairs"] > 0
    assert b.self_collision_stats["pairs"] == a.self_collision_stats["pairs"]
    moved = np.abs(a.positions - grid.positions).max()
    assert np.abs(b.positions - a.positions[perm]).max() <= tol * moved
    a.close()
    b.close()


@FULL
def test_restart_of_a_renumbered_run_continues_to_the_bit(small_window):
    base = cloth(10)
    floor = ms.Plane((0.0, 0.0, -0.2), (0.0, 0.0, 1.0), friction=0.5)
    model, _ = scrambled(ms.Model(base.positions, base.springs, masses=base.masses, stiffness=base.stiffness,
                                  damping=base.damping, rest_lengths=base.rest_lengths, gravity=base.gravity,
                                  fixed=base.fixed, pin_velocity=[[0.0, 0.0, -0.3]] * base.fixed.size,
                                  colliders=[floor]), 3)
    run = dict(integrator="bdf2", dt=1 / 60)
    whole = ms.Simulation(model, **run).step(10)
    assert whole.info()["order"] == "z-order"
    before = ms.Simulation(model, **run).step(4)
    part = ms.Simulation(model, **run).step(5)
    x, v, carried = part.positions, part.velocities, part.carried_state()
    # carried rows are the user's: the previous state is the run's step 4
    assert np.array_equal(carried["x_prev"], before.positions) and np.array_equal(carried["v_prev"], before.velocities)
    rest = ms.Simulation(model, **run).set_state(x, v, steps=5, carried=carried).step(5)
    assert np.array_equal(rest.positions, whole.positions) and np.array_equal(rest.velocities, whole.velocities)
    pinned = int(model.fixed[0])
    wrong = v.copy()
    wrong[pinned] = 0.0
    with pytest.raises(ValueError, match=f"particle {pinned} is pinned"):
        rest.set_state(x, wrong)
    for sim in (whole, before, part, rest):
        sim.close()


@FULL
def test_a_scrambled_obj_mesh_keeps_the_files_numbering_at_the_cli(tmp_path, capsys):
    """An OBJ whose vertices come in a scrambled order: ``massspring info`` says it is
    renumbered, and the exported frames list the vertices in the file's order, moving as
    those of the same mesh in grid order do (to round-off)."""
    grid = cloth(100)
    rng = np.random.default_rng(6)
    perm = rng.permutation(grid.n_particles)
    inverse = np.empty_like(perm)
    inverse[perm] = np.arange(len(perm))
    meshes = {"grid": (grid.positions, grid.triangles), "scrambled": (grid.positions[perm], inverse[grid.triangles])}
    last = {}
    for name, (vertices, triangles) in meshes.items():
        write_obj(tmp_path / f"{name}.obj", vertices, triangles[rng.permutation(len(triangles))])
        scene = tmp_path / f"{name}.toml"
        scene.write_text(f'description = "{name}"\nintegrator = "symplectic"\nduration = 1e-4\n[dt]\n'
                         f'symplectic = 2e-6\n[model]\nmesh = "{name}.obj"\ndensity = 0.2\nstiffness = 2000.0\n'
                         'pin_box = [[-10.0, 0.99, -10.0], [10.0, 10.0, 10.0]]\n')
        assert main(["info", str(scene)]) == 0
        said = capsys.readouterr().out
        assert ("renumbered in Z-order" in said) == (name == "scrambled"), said
        out = tmp_path / name
        assert main(["run", str(scene), "--steps", "40", "--every", "40", "--export", str(out), "--quiet"]) == 0
        frames = json.loads((out / "manifest.json").read_text())["frames"]
        first = read_obj(out / frames[0]["file"])
        assert np.array_equal(first.vertices, vertices)
        last[name] = read_obj(out / frames[-1]["file"]).vertices
    moved = np.abs(last["grid"] - grid.positions).max()
    assert moved > 1e-9
    assert np.abs(last["scrambled"] - last["grid"][perm]).max() <= 1e-12 * moved


def test_the_memory_check_counts_the_renumbered_copy(monkeypatch):
    """With room for a run of the model but not for a copy of its arrays too, a model
    that would be renumbered is refused before anything is built; one in good order runs."""
    from massspring.support import memory

    grid = cloth(100)
    model, _ = scrambled(grid, 7)
    run = memory.run_bytes(grid.n_particles, grid.n_springs, model_built=True)
    with_copy = memory.run_bytes(grid.n_particles, grid.n_springs, model_built=False)
    assert with_copy > run
    monkeypatch.setattr(memory, "available", lambda: ((run + with_copy) / 2, "of memory available"))
    built = []
    monkeypatch.setattr(ordering, "renumbered", lambda *args: built.append(args))
    with pytest.raises(memory.MemoryNeedError, match="model: 10,000 particles"):
        ms.Simulation(model, integrator="symplectic", dt=1e-6)
    assert not built
    ms.Simulation(grid, integrator="symplectic", dt=1e-6).close()
