"""Scenes: generators keep total mass and physics across resolutions; loading and overrides."""

import re

import numpy as np
import pytest

import massspring as ms
from massspring.integrators import INTEGRATORS
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
    with pytest.raises(ValueError, match="preconditioner: unknown value 'jacobi'"):  # before the memory estimate
        scene.simulation(integrator="bdf2", preconditioner="jacobi")


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
    assert scene.default_dt("midpoint") == pytest.approx(1 / 60)  # 2 / omega = 0.2 s: the frame is smaller
    stiff = ms.load_scene(path).with_params(stiffness=1e6)
    assert stiff.default_dt("midpoint") == pytest.approx(2 / predict(stiff.model()).omega_max, rel=1e-9)
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


def test_a_scenes_tol_is_the_default_that_fixed_step_arguments_give_way_to(tmp_path):
    """``tol``: a number is every integrator's, a [tol] table the named ones'; a run
    given dt, newton_tol or cg_tol (options of fixed steps) or tol=None steps fixed."""
    chain = '[model]\ngenerator = "chain"\ncount = 5\n'
    every, named = tmp_path / "every.toml", tmp_path / "named.toml"
    every.write_text(f'integrator = "implicit"\nduration = 2.0\ntol = 0.01\n{chain}')
    named.write_text(f'integrator = "implicit"\nduration = 2.0\n[tol]\nbdf2 = 0.001\n{chain}')

    def settings(scene, *args, **kwargs):
        sim = scene.simulation(*args, **kwargs)
        try:
            return sim.settings.tol, sim.settings.horizon, sim.dt
        finally:
            sim.close()

    scene = ms.load_scene(every)
    assert scene.tol == dict.fromkeys(INTEGRATORS, 0.01)
    assert settings(scene) == (0.01, 2.0, scene.default_dt())
    assert settings(scene, "symplectic") == (0.01, 2.0, scene.default_dt("symplectic"))
    assert settings(scene, horizon=1.0, tol=1e-3) == (1e-3, 1.0, scene.default_dt())
    for fixed in ({"dt": 1e-3}, {"cg_tol": 1e-4}, {"tol": None}, {"tol": None, "horizon": 1.0}):
        assert settings(scene, **fixed)[:2] == (None, None), fixed
    assert settings(scene, "bdf2", newton_tol=1e-4)[:2] == (None, None)
    assert settings(scene, dt=1e-3, tol=0.01) == (0.01, 2.0, 1e-3)  # tol given: dt is its first step
    scene = ms.load_scene(named)
    assert scene.tol == {"bdf2": 0.001}
    assert settings(scene)[:2] == (None, None)
    assert settings(scene, "bdf2")[:2] == (0.001, 2.0)


@pytest.mark.parametrize("body, message", [
    ('tol = "fine"', "tol: expected a number or a table, got str"), ("tol = 0", "tol: "),
    ("tol = 1e-15", "tol: .*below 1e-14"), ("[tol]\nfast = 0.1", "tol.fast: unknown integrator"),
    ("[tol]\nbdf2 = -1.0", "tol.bdf2: "), ('[tol]\nbdf2 = "0.1"', "tol.bdf2: expected a number"),
])
def test_bad_tol_names_the_key(body, message, tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text(f'integrator = "implicit"\nduration = 1.0\n{body}\n[model]\ngenerator = "spring"\n')
    with pytest.raises(ms.SceneError, match=f"^{re.escape(str(path))}: {message}"):
        ms.load_scene(path)


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


# ----------------------------------------------------------------------------- contact, pins and air


CONTACT_SCENES = {"drape": ("plane", "sphere"), "tablecloth": ("plane", "box"), "flag": ("box", "plane"),
                  "rope-drop": ("plane", "sphere"), "swing": (), "cube": ("plane",)}


@pytest.mark.parametrize("name", sorted(CONTACT_SCENES))
def test_contact_scenes_build_their_colliders_pins_and_air(name):
    scene = ms.load_scene(name)
    small = {"chain": {"count": 6}, "lattice": {"resolution": 3}}.get(scene.generator, {"resolution": 5})
    model = scene.with_params(**small).model()
    assert tuple(c.kind for c in model.colliders) == CONTACT_SCENES[name]
    if name == "flag":
        assert model.has_drag and np.any(model.wind != 0)
        assert np.allclose(model.positions[:, 1], 0.0)  # upright: in the y = 0 plane
        assert np.allclose(model.positions[model.fixed, 0], 0.0) and model.fixed.size == 5  # along the pole
        pole = model.colliders[0]  # beside the pinned edge, clear of the cloth, standing on the ground
        assert pole.upper[0] < 0 and pole.lower[2] == model.colliders[1].point[2]
        assert pole.lower[2] < model.positions[:, 2].min() and pole.upper[2] > model.positions[:, 2].max()
    if name == "cube":  # the ground is below the cube, which reaches it (duration) after 100 steps
        gap = model.positions[:, 2].min() - model.colliders[0].point[2]
        fall = np.sqrt(2 * gap / 9.81)
        assert 100 * scene.default_dt() < fall < scene.duration
    if name == "swing":
        last = model.n_particles - 1
        np.testing.assert_array_equal(model.pin_velocity[list(model.fixed).index(last)], [-0.2, -0.8, 0.3])
        np.testing.assert_array_equal(model.pin_velocity[0], [0.0, -0.8, 0.3])
    if name == "rope-drop":
        assert model.fixed.size == 0


def scene_file(tmp_path, body, model='generator = "chain"\ncount = 4'):
    path = tmp_path / "scene.toml"
    path.write_text(f'integrator = "implicit"\nduration = 1.0\n[model]\n{model}\n{body}\n')
    return path


@pytest.mark.parametrize("body, key", [
    ('[[collider]]\nradius = 1.0', "collider[0].type"),
    ('[[collider]]\ntype = "cylinder"', "collider[0].type"),
    ('[[collider]]\ntype = "sphere"\ncenter = [0, 0, 0]', "collider[0].radius"),
    ('[[collider]]\ntype = "sphere"\ncenter = [0, 0, 0]\nradius = -1.0', "collider[0].radius"),
    ('[[collider]]\ntype = "sphere"\ncenter = [0, 0]\nradius = 1.0', "collider[0].center"),
    ('[[collider]]\ntype = "plane"\npoint = [0, 0, 0]\nnormal = [0, 0, 1]\n'
     '[[collider]]\ntype = "plane"\npoint = [0, 0, 0]\nnormal = [0, 0, 0]', "collider[1].normal"),
    ('[[collider]]\ntype = "box"\nlower = [0, 0, 0]\nupper = [1, 1, 1]\nfriction = -1', "collider[0].friction"),
    ('[[collider]]\ntype = "box"\nlower = [0, 0, 0]\nupper = [1, 1, 1]\nrestitution = 2', "collider[0].restitution"),
    ('[[collider]]\ntype = "box"\nlower = [0, 0, 0]\nupper = [1, 0, 1]', "collider[0].lower"),
    ('[[collider]]\ntype = "box"\nlower = [0, 0, 0]\nupper = [1, 1, 1]\nheight = 2', "collider[0].height"),
    ('[[pin]]\nvelocity = [0, 0, 1]', "pin[0].index"),
    ('[[pin]]\nindex = 1\nvelocity = [0, 1]', "pin[0].velocity"),
    ('[[pin]]\nindex = 1\nspeed = 2.0', "pin[0].speed"),
    ('[controls]\nwind = [[1, 0, 0]]', "controls.interval"),
    ('[controls]\ninterval = 0.1\ngust = 1', "controls.gust"),
    ('[controls]\ninterval = 0.1\nwind = [[1, 0]]', "controls.wind"),
    ('[controls]\ninterval = 0.1\nwind = [[1, 0, 0]]', "controls.wind"),  # the chain has no drag
    ('[controls]\ninterval = 0.1\npin_targets = [[[0, 0, 0], [1, 0, 0]]]', "controls.pin_targets"),  # one pin
    ('[controls]\ninterval = "long"\nwind = [[1, 0, 0]]', "controls.interval"),
])
def test_bad_collider_and_pin_tables_name_the_key_and_file(tmp_path, body, key):
    path = scene_file(tmp_path, body)
    with pytest.raises(ms.SceneError) as info:
        ms.load_scene(path).model()
    assert key in str(info.value) and str(path) in str(info.value), info.value


def test_controls_of_a_scene_file_are_the_python_ones_and_run(tmp_path, capsys):
    """A [controls] table gives the model the Controls its keys describe; the CLI runs it
    (pins to their keyframes) and refuses a dt that does not divide the interval (exit 2,
    naming dt)."""
    from massspring.cli import main

    path = scene_file(tmp_path, "[controls]\ninterval = 0.05\nwind = [[1, 0, 0], [0, 2, 0]]\n"
                                "pin_targets = [[[0, 0, 0.1]], [[0, 0, 0.2]]]",
                      'generator = "chain"\ncount = 4\ndrag = 0.1')
    model = ms.load_scene(path).model()
    assert model.controls.interval == 0.05 and model.has_moving_pins
    np.testing.assert_array_equal(model.controls.wind, [[1, 0, 0], [0, 2, 0]])
    np.testing.assert_array_equal(model.controls.pin_targets, [[[0, 0, 0.1]], [[0, 0, 0.2]]])
    out = tmp_path / "state.npz"
    assert main(["run", str(path), "--dt", "0.01", "--steps", "12", "--quiet", "--out", str(out)]) == 0
    np.testing.assert_allclose(np.load(out)["positions"][model.fixed[0]], [0, 0, 0.2], atol=1e-12)
    capsys.readouterr()
    assert main(["run", str(path), "--dt", "0.03", "--steps", "2", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "dt: controls.interval 0.05 s is not a whole number of steps of 0.03 s" in err and "Traceback" not in err


def test_pin_index_out_of_range_is_named(tmp_path):
    scene = ms.load_scene(scene_file(tmp_path, "[[pin]]\nindex = -9"))
    with pytest.raises(ms.SceneError, match=r"pin\[0\]\.index: -9 is outside"):
        scene.model()


def test_pins_and_pin_velocity_of_a_scene(tmp_path):
    """[[pin]] pins its particle (negative: from the end) with its velocity; pin_velocity moves
    the generator's pins."""
    scene = ms.load_scene(scene_file(tmp_path, "[[pin]]\nindex = -1\nvelocity = [0, 0, 2]",
                                     'generator = "chain"\ncount = 4\npin_velocity = [1, 0, 0]'))
    model = scene.model()
    assert model.fixed.tolist() == [0, 3]
    np.testing.assert_array_equal(model.pin_velocity, [[1, 0, 0], [0, 0, 2]])


def test_common_keys_work_with_every_generator_and_set():
    """drag, wind and pin_velocity are model keys of any generator, in files and with --set."""
    for name in ("spring", "chain", "cloth", "cube"):
        scene = ms.load_scene(name).with_settings(["drag=0.5", "wind=[1, 0, 0]"])
        assert scene.common["drag"] == 0.5 and scene.common["wind"] == [1.0, 0.0, 0.0]
        assert "drag" not in scene.params
    model = ms.load_scene("cloth").with_settings(["drag=0.5", "resolution=4"]).model()
    assert model.drag == 0.5 and np.all(model.wind == 0)
    with pytest.raises(ms.SceneError, match="--set wind"):
        ms.load_scene("cloth").with_settings(["wind=[1, 0, 0]", "resolution=4"]).model()
    for bad in (["drag=-1"], ["drag=fast"], ["wind=[1, 0]"], ["pin_velocity=[0, 0, inf]"]):
        with pytest.raises(ms.SceneError, match=bad[0].split("=")[0]):
            ms.load_scene("cloth").with_settings(bad)


def test_grid_upright_side_pin_and_chain_without_pin():
    from massspring.scene import generators

    args = generators.grid(**dict(generators.PARAMETERS["grid"], resolution=3, pin="side", upright=True))
    x = np.asarray(args["positions"])
    assert np.allclose(x[:, 1], 0.0) and np.ptp(x[:, 2]) == pytest.approx(1.0)
    assert np.allclose(x[args["fixed"], 0], 0.0) and len(args["fixed"]) == 3
    chain = generators.chain(**dict(generators.PARAMETERS["chain"], pin="none"))
    assert len(chain["fixed"]) == 0
    with pytest.raises(ValueError, match="pin"):
        generators.chain(**dict(generators.PARAMETERS["chain"], pin="middle"))


@pytest.mark.full
def test_rope_drop_lands_on_the_ball_and_slides_off():
    """What rope-drop's description says, at its defaults: particles rest on the ball
    after the fall (0.6 s), none from 1.5 s on."""
    scene = ms.load_scene("rope-drop")
    ball = next(c for c in scene.colliders if c.kind == "sphere")
    sim = scene.simulation()

    def on_ball():
        return int((np.linalg.norm(sim.positions - ball.center, axis=1) < ball.radius + 0.01).sum())

    sim.step(round(0.6 / sim.dt))
    assert on_ball() >= 5
    sim.step(round(1.5 / sim.dt) - sim.steps)
    assert on_ball() == 0
    sim.close()


def test_errors_about_a_built_in_scene_name_it_not_its_file():
    """Issue 42: the memory refusal of ``run cloth --set resolution=...`` named a
    site-packages path (the installed scene file) instead of the scene."""
    scene = ms.load_scene("cloth")
    assert scene.builtin and scene.label == "scene 'cloth'"
    with pytest.raises(ValueError, match=r"^scene 'cloth': model: resolution = 20000 gives 400,000,000 particles"):
        scene.with_params(resolution=20000).simulation()
    copy = ms.load_scene(scene.source)  # the same file by its path: a file of the user's
    assert not copy.builtin and copy.label == scene.source
