"""Scenes: generators keep total mass and physics across resolutions; loading and overrides."""

import numpy as np
import pytest

import massspring as ms
from massspring.scene import generators


def test_load_builtin_and_path(tmp_path):
    scene = ms.load_scene("cloth")
    assert scene.generator == "grid" and scene.integrator == "implicit"
    copy = tmp_path / "mine.toml"
    copy.write_text(open(scene.source).read())
    assert ms.load_scene(copy).params == scene.params


@pytest.mark.parametrize("name, key", [("cloth", "resolution"), ("cube", "resolution"), ("chain", "count")])
def test_resolution_keeps_total_mass(name, key):
    scene = ms.load_scene(name)
    for value in (3, 5):
        model = scene.with_params(**{key: value}).model()
        assert model.masses.sum() == pytest.approx(scene.params["mass"], rel=1e-12)


def test_chain_stiffness_scales_with_spacing():
    # A chain of N springs in series with ks = EA / h stretches by the same total
    # amount under the same end load at any resolution: 1/sum(1/ks) = EA / length.
    scene = ms.load_scene("chain")
    for count in (5, 17):
        model = scene.with_params(count=count).model()
        series = 1.0 / np.sum(1.0 / model.stiffness)
        assert series == pytest.approx(scene.params["stiffness"] / scene.params["length"], rel=1e-12)


def test_cloth_springs_and_pins():
    model = ms.load_scene("cloth").with_params(resolution=4).model()
    r = 4
    structural, shear, bend = 2 * r * (r - 1), 2 * (r - 1) ** 2, 2 * r * (r - 2)
    assert model.n_springs == structural + shear + bend
    assert model.fixed.tolist() == [12, 15]  # the two corners of the last row (y = size)
    assert np.allclose(model.positions[model.fixed, 1], 1.0)


def test_cube_has_all_13_directions():
    model = ms.load_scene("cube").with_params(resolution=2, squash=1.0, spin=0.0).model()
    assert model.n_springs == 28  # every pair of the 8 corners of one cell
    assert np.allclose(model.rest_lengths, np.linalg.norm(
        model.positions[model.springs[:, 1]] - model.positions[model.springs[:, 0]], axis=1))


def test_settings_are_typed():
    scene = ms.load_scene("cloth").with_settings(["resolution=8", "stiffness=1e5", "pin=edge"])
    assert scene.params["resolution"] == 8 and scene.params["stiffness"] == 1e5
    assert scene.params["pin"] == "edge"
    with pytest.raises(ValueError, match="pin"):
        scene.with_settings(["pin=middle"]).model()
    with pytest.raises(ValueError, match="resolution"):
        scene.with_settings(["resolution=abc"])


def test_simulation_uses_scene_dt():
    scene = ms.load_scene("spring")
    assert scene.simulation(integrator="explicit").dt == scene.dt["explicit"]
    assert scene.simulation().dt == scene.dt["implicit"]
    assert scene.simulation(dt=0.5).dt == 0.5
    with pytest.raises(ValueError, match="integrator"):
        scene.simulation(integrator="leapfrog")


def test_integrators_without_a_scene_dt_get_one_from_the_stability_estimate(tmp_path):
    """A [dt] table names some integrators; the others get Integrator.suggest_dt of the
    stability prediction: half the symplectic limit 2/omega for one undamped spring
    (omega = sqrt(ks/m) = 10 rad/s), half RK4's imaginary-axis limit 2.83/omega."""
    from massspring.analysis.stability import predict

    text = ms.load_scene("spring").source
    body = open(text).read().split("[dt]")[0] + "[model]" + open(text).read().split("[model]")[1]
    path = tmp_path / "nodt.toml"
    path.write_text(body)
    scene = ms.load_scene(path).with_params(damping=0.0)
    assert scene.dt == {}
    omega = predict(scene.model()).omega_max
    assert omega == pytest.approx(10.0, rel=1e-6)
    assert scene.default_dt("symplectic") == pytest.approx(0.5 * 2 / omega, rel=1e-9)
    assert scene.default_dt("rk4") == pytest.approx(0.5 * 2 * np.sqrt(2) / omega, rel=1e-9)
    assert scene.default_dt("implicit") == pytest.approx(1 / 60)
    sim = scene.simulation(integrator="symplectic")
    sim.step(100)  # stable at its suggested dt
    assert np.all(np.isfinite(sim.positions)) and sim.energy()["total"] <= 1.01 * scene.model().energy(
        scene.model().positions, scene.model().velocities)["total"]


@pytest.mark.parametrize("settings, key", [(["seed=-5"], "seed"), (["count=2", "count=3"], "count"),
                                           (["resolution=[3]"], "resolution")])
def test_bad_settings_name_the_key(settings, key):
    scene = ms.load_scene("chain" if "count" in key else "cloth")
    with pytest.raises(ValueError) as info:
        scene.with_settings(settings).model()
    assert key in str(info.value)


@pytest.mark.parametrize("body, key", [
    ('generator = ["grid"]', "model.generator"), ("generator = { a = 1 }", "model.generator"),
    ('generator = "grid"\nresolution = 2.5', "model.resolution"),
    ('generator = "grid"\nsize = inf', "model.size"),
])
def test_bad_model_table_names_the_key(body, key, tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text(f'integrator = "implicit"\nduration = 1.0\n[model]\n{body}\n')
    with pytest.raises(ms.SceneError) as info:
        ms.load_scene(path).model()
    assert key in str(info.value) and str(path) in str(info.value)


@pytest.mark.parametrize("duration", ["inf", "-1.0", "nan", "0.0"])
def test_duration_must_be_finite_and_positive(duration, tmp_path):
    path = tmp_path / "d.toml"
    path.write_text(f'integrator = "implicit"\nduration = {duration}\n[model]\ngenerator = "spring"\n')
    with pytest.raises(ms.SceneError, match="duration"):
        ms.load_scene(path)


def test_generators_parameters_match_signatures():
    import inspect
    for name, fn in generators.GENERATORS.items():
        assert list(inspect.signature(fn).parameters) == list(generators.PARAMETERS[name])


def test_solver_table_sets_simulation_defaults_that_arguments_override(tmp_path):
    path = tmp_path / "s.toml"
    path.write_text('integrator = "implicit"\nduration = 1.0\n[solver]\npreconditioner = "multigrid"\n'
                    'cg_tol = 1e-8\ncg_max_iter = 500\ndefiniteness_fix = false\n'
                    '[model]\ngenerator = "chain"\ncount = 5\n')
    scene = ms.load_scene(path)
    sim = scene.simulation()
    assert (sim.preconditioner, sim.cg_tol, sim.cg_max_iter, sim.definiteness_fix) == ("multigrid", 1e-8, 500, False)
    sim.close()
    sim = scene.simulation(preconditioner="none", cg_tol=1e-4)
    assert (sim.preconditioner, sim.cg_tol, sim.cg_max_iter) == ("none", 1e-4, 500)
    sim.close()


@pytest.mark.parametrize("body, key", [
    ('preconditioner = "amg"', "solver.preconditioner"), ("preconditioner = 3", "solver.preconditioner"),
    ("cg_tol = 1.5", "solver.cg_tol"), ("cg_tol = nan", "solver.cg_tol"), ("cg_max_iter = 0", "solver.cg_max_iter"),
    ("cg_max_iter = 2.5", "solver.cg_max_iter"), ('definiteness_fix = "yes"', "solver.definiteness_fix"),
    ("tolerance = 1e-6", "solver.tolerance"),
])
def test_bad_solver_table_names_the_key(body, key, tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text(f'integrator = "implicit"\nduration = 1.0\n[solver]\n{body}\n[model]\ngenerator = "spring"\n')
    with pytest.raises(ms.SceneError) as info:
        ms.load_scene(path)
    assert key in str(info.value) and str(path) in str(info.value)
