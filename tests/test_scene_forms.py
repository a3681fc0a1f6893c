"""Scene files that bring their own model: an OBJ mesh (``[model] mesh``) or hand-made
``[particles]`` and ``[springs]`` tables; each refused case names the file and key (or line)."""

import numpy as np
import pytest

import massspring as ms
from massspring.cli import main

HEAD = 'description = "test"\nintegrator = "symplectic"\nduration = 0.01\n[dt]\nsymplectic = 1e-3\n'


def square_obj(path, r=4):
    """An r x r quad grid in the z = 0 plane of side 1 m, as OBJ; returns (vertices, faces)."""
    g = np.arange(r) / (r - 1)
    vertices = np.stack([np.tile(g, r), np.repeat(g, r), np.zeros(r * r)], axis=1)
    idx = np.arange(r * r).reshape(r, r)
    faces = np.stack([idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]], axis=-1).reshape(-1, 4)
    path.write_text("".join(f"v {x!r} {y!r} {z!r}\n" for x, y, z in vertices.tolist()) +
                    "".join("f " + " ".join(str(i + 1) for i in face) + "\n" for face in faces.tolist()))
    return vertices, faces


def write_scene(tmp_path, body, name="scene.toml"):
    path = tmp_path / name
    path.write_text(HEAD + body)
    return path


def test_mesh_scene_reads_the_obj_next_to_the_scene_file(tmp_path, monkeypatch):
    (tmp_path / "meshes").mkdir()
    vertices, faces = square_obj(tmp_path / "meshes" / "cloth.obj")
    path = write_scene(tmp_path, '[model]\nmesh = "meshes/cloth.obj"\ndensity = 0.3\nstiffness = 500.0\n'
                       'bend = 0.2\nfixed = [0]\npin_box = [[0.9, 0.9, -1], [2, 2, 1]]\ngravity = [0, 0, -1.62]\n')
    monkeypatch.chdir("/")
    scene = ms.load_scene(path)
    assert scene.form == "mesh" and scene.generator is None
    expected = ms.Model.from_mesh(vertices, faces, density=0.3, stiffness=500.0, bend=0.2, fixed=[0],
                                  pin_box=[[0.9, 0.9, -1], [2, 2, 1]], gravity=[0, 0, -1.62])
    model = scene.model()
    assert model.fingerprint() == expected.fingerprint()
    assert model.fixed.tolist() == [0, 15] and model.masses.sum() == pytest.approx(0.3)
    assert np.array_equal(model.triangles, expected.triangles)


def test_mesh_scene_mass_or_density(tmp_path):
    square_obj(tmp_path / "cloth.obj")
    scene = ms.load_scene(write_scene(tmp_path, '[model]\nmesh = "cloth.obj"\nmass = 2.0\n'))
    assert scene.model().masses.sum() == pytest.approx(2.0)
    denser = scene.with_settings(["density=5.0"])  # replaces the file's mass
    assert denser.params["mass"] is None and denser.model().masses.sum() == pytest.approx(5.0)
    assert ms.load_scene(write_scene(tmp_path, '[model]\nmesh = "cloth.obj"\n')).model().masses.sum() == \
        pytest.approx(1.0)
    with pytest.raises(ms.SceneError, match="model.density, model.mass: give one"):
        ms.load_scene(write_scene(tmp_path, '[model]\nmesh = "cloth.obj"\nmass = 2.0\ndensity = 1.0\n'))


@pytest.mark.parametrize("obj, words", [
    (None, ["scene.toml: model.mesh:", "cloth.obj: cannot be read"]),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n", ["cloth.obj:4: vertex index 4 is beyond"]),
    ("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n", ["cloth.obj:4: degenerate face"]),
    ("# nothing\n", ["scene.toml: model.mesh:", "cloth.obj: no vertices"]),
])
def test_bad_obj_fails_when_the_scene_loads_naming_file_and_line(obj, words, tmp_path, capsys):
    if obj is not None:
        (tmp_path / "cloth.obj").write_text(obj)
    path = write_scene(tmp_path, '[model]\nmesh = "cloth.obj"\n')
    with pytest.raises(ms.SceneError) as info:
        ms.load_scene(path)
    for word in words:
        assert word in str(info.value), str(info.value)
    assert main(["run", str(path), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err and words[-1] in err


@pytest.mark.parametrize("body, words", [
    ('[model]\nmesh = "cloth.obj"\nfixed = [99]\n', ["model.fixed", "99"]),
    ('[model]\nmesh = "cloth.obj"\nfixed = [1.5]\n', ["model.fixed", "integer"]),
    ('[model]\nmesh = "cloth.obj"\npin_box = [0, 1]\n', ["model.pin_box", "two corners"]),
    ('[model]\nmesh = "cloth.obj"\npin_box = [[5, 5, 5], [6, 6, 6]]\n', ["model.pin_box", "no vertex"]),
    ('[model]\nmesh = "cloth.obj"\nbend = -1.0\n', ["model.bend", ">= 0"]),
    ('[model]\nmesh = "cloth.obj"\nresolution = 4\n', ["model.resolution", "unknown parameter of a mesh scene"]),
    ('[model]\nmesh = 5\n', ["model.mesh", "expected a string"]),
    ('[model]\nmesh = "cloth.obj"\ngenerator = "grid"\n', ["model.generator and model.mesh", "only one"]),
])
def test_bad_mesh_parameters_name_the_key(body, words, tmp_path):
    square_obj(tmp_path / "cloth.obj")
    with pytest.raises(ms.SceneError) as info:
        ms.load_scene(write_scene(tmp_path, body)).model()
    for word in words:
        assert word in str(info.value), str(info.value)
    assert "scene.toml" in str(info.value)


HANDMADE = ('[model]\ngravity = [0, 0, -1]\ntriangles = [[0, 1, 2]]\n'
            '[particles]\npositions = [[0, 0, 0], [1, 0, 0], [0, 2, 0]]\nmasses = [1, 2, 3]\n'
            'velocities = [[0, 0, 0], [0, 0, 1], [0, 0, 0]]\nfixed = [0]\n'
            '[springs]\npairs = [[0, 1], [1, 2], [2, 0]]\nstiffness = 50.0\ndamping = [0.1, 0.2, 0.3]\n')


def test_hand_made_scene_gives_the_model_it_writes(tmp_path):
    scene = ms.load_scene(write_scene(tmp_path, HANDMADE))
    assert scene.form == "particles"
    model = scene.model()
    assert model.positions.tolist() == [[0, 0, 0], [1, 0, 0], [0, 2, 0]]
    assert model.masses.tolist() == [1, 2, 3] and model.fixed.tolist() == [0]
    assert model.velocities.tolist() == [[0, 0, 0], [0, 0, 1], [0, 0, 0]]
    assert model.springs.tolist() == [[0, 1], [1, 2], [2, 0]]
    assert model.stiffness.tolist() == [50.0] * 3 and model.damping.tolist() == [0.1, 0.2, 0.3]
    assert model.rest_lengths == pytest.approx([1.0, 5 ** 0.5, 2.0])  # the initial distances
    assert model.gravity.tolist() == [0, 0, -1] and model.triangles.tolist() == [[0, 1, 2]]
    assert scene.with_settings(["gravity=[0, 0, 0]"]).model().gravity.tolist() == [0, 0, 0]
    rest = ms.load_scene(write_scene(tmp_path, HANDMADE.replace("damping = [0.1, 0.2, 0.3]", "rest_lengths = 0.5")))
    assert rest.model().rest_lengths.tolist() == [0.5] * 3


def test_hand_made_scene_runs_from_the_command_line(tmp_path, capsys):
    out = tmp_path / "state.npz"
    assert main(["run", str(write_scene(tmp_path, HANDMADE)), "--quiet", "--out", str(out)]) == 0
    assert int(np.load(out)["steps"]) == 10


@pytest.mark.parametrize("change, words", [
    (("masses = [1, 2, 3]", "masses = [1, 2]"), ["particles.masses", "shape"]),
    (("pairs = [[0, 1], [1, 2], [2, 0]]", "pairs = [[0, 1], [1, 2], [2, 7]]"), ["springs.pairs", "outside"]),
    (("pairs = [[0, 1], [1, 2], [2, 0]]", "pairs = [0, 1]"), ["springs.pairs", "expected a list"]),
    (('positions = [[0, 0, 0], [1, 0, 0], [0, 2, 0]]', 'positions = [[0, 0, 0], [1, 0, "x"], [0, 2, 0]]'),
     ["particles.positions", "expected a number"]),
    (("fixed = [0]", "fixed = [5]"), ["particles.fixed", "outside"]),
    (("fixed = [0]", "fixed = 0"), ["particles.fixed", "expected a list"]),
    (("stiffness = 50.0", "stiffness = -50.0"), ["springs.stiffness", ">= 0"]),
    (("stiffness = 50.0", "stifness = 50.0"), ["springs.stifness", "unknown key"]),
    (("triangles = [[0, 1, 2]]", "triangles = [[0, 1, 5]]"), ["model.triangles", "outside"]),
    (("[springs]\npairs = [[0, 1], [1, 2], [2, 0]]\n", "[springs]\n"), ["springs.pairs", "missing"]),
    (("[model]\n", '[model]\ngenerator = "grid"\n'), ["model.generator and [particles] and [springs]"]),
])
def test_bad_hand_made_scenes_name_the_key(change, words, tmp_path):
    path = write_scene(tmp_path, HANDMADE.replace(*change))
    with pytest.raises(ms.SceneError) as info:
        ms.load_scene(path).model()
    for word in words:
        assert word in str(info.value), str(info.value)
    assert str(path) in str(info.value)


def test_a_scene_without_a_model_says_what_is_missing(tmp_path):
    with pytest.raises(ms.SceneError, match="missing key 'model'.*particles"):
        ms.load_scene(write_scene(tmp_path, ""))
    with pytest.raises(ms.SceneError, match="model.generator.*model.mesh"):
        ms.load_scene(write_scene(tmp_path, "[model]\nsize = 1.0\n"))


def test_set_mesh_reads_another_file_relative_to_the_working_directory(tmp_path, monkeypatch):
    square_obj(tmp_path / "cloth.obj", r=4)
    (tmp_path / "other").mkdir()
    square_obj(tmp_path / "other" / "fine.obj", r=6)
    scene = ms.load_scene(write_scene(tmp_path, '[model]\nmesh = "cloth.obj"\n'))
    monkeypatch.chdir(tmp_path / "other")
    assert scene.with_settings(["mesh=fine.obj"]).model().n_particles == 36
    with pytest.raises(ms.SceneError, match="none.obj: cannot be read"):
        scene.with_settings(["mesh=none.obj"])


def test_info_names_the_form(tmp_path, capsys):
    square_obj(tmp_path / "cloth.obj")
    assert main(["info", str(write_scene(tmp_path, '[model]\nmesh = "cloth.obj"\n', "m.toml"))]) == 0
    assert f"mesh        {tmp_path / 'cloth.obj'}: density=None, mass=None" in capsys.readouterr().out
    assert main(["info", str(write_scene(tmp_path, HANDMADE, "h.toml"))]) == 0
    text = capsys.readouterr().out
    assert "model       hand-made ([particles] and [springs])" in text and "3 particles, 3 springs, 1 fixed" in text
