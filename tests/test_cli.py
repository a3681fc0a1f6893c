"""The command line: every built-in scene runs, bad input exits 2 with a one-line message."""

import os
import subprocess
import sys

import numpy as np
import pytest

from conftest import FULL, one_line_error, sampled
from massspring.cli import main
from massspring.integrators import INTEGRATORS
from massspring.scene import builtin_scenes, load_scene
from test_scene_energy import ENERGY_RUNS, WHOLE_RUNS
from test_self_collision import SHIPPED_RUNS

# The fast tier: each scene once with its default integrator, each integrator on two scenes.
TWO_SCENES = {"explicit": ("chain", "cloth"), "symplectic": ("spring", "chain"), "rk4": ("chain", "heavychain"),
              "implicit": ("stiffcloth", "bigstep"), "backward-euler": ("cloth", "chain"),
              "bdf2": ("stiffchain", "swing"), "midpoint": ("chain", "heavychain")}
RESET_BETWEEN_TESTS = True  # conftest: each test compiles its own configuration and shares no simulation
# (the self-collision scenes but sheets in the full tier: each compiles the pass, 6 s)
FAST_RUNS = {(scene, load_scene(scene).integrator) for scene in builtin_scenes()
             if scene not in ("ledge", "tablecloth", "thrown")} | {
    (scene, integrator) for integrator in INTEGRATORS for scene in TWO_SCENES.get(integrator, ("spring", "chain"))}


def run_cli(*args):
    """The CLI in a subprocess (as a user runs it): (exit code, stdout, stderr)."""
    proc = subprocess.run([sys.executable, "-m", "massspring", *args], capture_output=True, text=True)
    return proc.returncode, proc.stdout, proc.stderr


# test_scene_energy runs these whole (every small scene, every integrator, its whole duration
# at its default dt): here only those of the fast tier, for the CLI's side
WHOLE = set(WHOLE_RUNS + ENERGY_RUNS) - FAST_RUNS
# The self-collision scenes' 3-step backward-Euler runs (5-6 s each, their compiles) are
# BDF2's, whose first step is backward Euler's; test_self_collision runs backward Euler
# on self-collision at length, and runs these scenes and integrators longer, at their
# default dt, checking every sampled frame for crossings (its SHIPPED_RUNS)
SHARED = ({(scene, "backward-euler") for scene in ("ledge", "sheets", "tablecloth", "thrown")}
          | {(name, integrator) for name, _, integrator, _, _ in SHIPPED_RUNS}) - FAST_RUNS


@pytest.mark.parametrize("scene, integrator", sampled(
    [(scene, integrator) for scene in sorted(builtin_scenes()) for integrator in sorted(INTEGRATORS)
     if (scene, integrator) not in WHOLE | SHARED], FAST_RUNS))
def test_run_every_scene(scene, integrator, tmp_path, capsys):
    """Every scene runs with every integrator at its default dt from the CLI. Integrators
    with a stability limit run the scene at its own size for 100 steps (a default dt that
    does not hold fails soon: steps 3 to 96 where they were wrong or cannot hold); the
    others, whose steps cost more, run 3 steps of a smaller model. The small scenes' runs
    of the full suite are ``test_scene_energy``'s, of their whole duration."""
    out = tmp_path / "state.npz"
    limited = not INTEGRATORS[integrator].traits.linear_solver
    if (scene, integrator) == ("stiffchain", "explicit"):
        # undamped: explicit Euler grows an undamped oscillation at every dt (|1 + i w dt| > 1), the
        # scene's point; its run must stop as diverged (exit 3, one line) with a dt and integrators to try
        assert main(["run", scene, "--integrator", integrator, "--steps", "100", "--quiet"]) == 3
        one_line_error(capsys, "explicit diverged at step", "--dt", "--integrator")
        return
    grid = ["--set", "resolution=6"]
    small = {} if limited else {
        "cloth": grid, "drape": grid, "tablecloth": grid, "flag": grid, "swing": grid, "sheets": grid,
        "ledge": grid, "thrown": grid, "cube": ["--set", "resolution=3"], "chain": ["--set", "count=5"],
        "rope-drop": ["--set", "count=5"]}
    steps = 100 if limited else 3
    code = main(["run", scene, "--integrator", integrator, "--steps", str(steps), "--quiet", "--out", str(out),
                 *small.get(scene, [])])
    assert code == 0
    text = capsys.readouterr().out
    assert f"steps       {steps}" in text
    assert ("CG " in text) == INTEGRATORS[integrator].traits.linear_solver
    data = np.load(out)
    assert data["positions"].shape == data["velocities"].shape
    assert np.all(np.isfinite(data["positions"]))
    assert data["steps"] == steps


def test_scenes_lists_builtins():
    code, out, err = run_cli("scenes")
    assert code == 0, err
    names = [line.split()[0] for line in out.splitlines()]
    assert names == sorted(builtin_scenes())


def test_info_names_compiled_terms(capsys):
    assert main(["info", "spring"]) == 0
    text = capsys.readouterr().out
    assert "terms       spring, damping, fixed-filter" in text  # spring scene: no gravity
    assert main(["info", "cube", "--integrator", "explicit", "--set", "resolution=3"]) == 0
    text = capsys.readouterr().out
    terms = next(line for line in text.splitlines() if line.startswith("terms"))
    assert "fixed-filter" not in terms and "gravity" in terms
    arrays = next(line for line in text.splitlines() if line.startswith("arrays"))
    assert "minv" not in arrays and " p," not in arrays


@FULL
def test_info_warns_of_a_scene_dt_above_the_stability_limit_at_the_size_asked(capsys):
    """Issue 42: ``info cloth --set resolution=128`` listed the scene's explicit dt, which
    diverges at that size, without a word; now it says so and gives a dt."""
    assert main(["info", "cloth"]) == 0
    assert "stability limit" not in capsys.readouterr().out  # the dt the scene was made for holds
    assert main(["info", "cloth", "--set", "resolution=128"]) == 0
    line = next(line for line in capsys.readouterr().out.splitlines() if line.startswith("dt defaults"))
    explicit = line.split(", symplectic")[0]
    assert "above its stability limit" in explicit and "--dt " in explicit, line


def test_bad_scene_file_names_key(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text('integrator = "implicit"\nduration = 1.0\n[dt]\nexplicit = 1e-3\nsymplectic = 1e-3\n'
                    'implicit = 1e-2\n[model]\ngenerator = "chain"\ncount = 5\nstifness = 10.0\n')
    code, out, err = run_cli("run", str(path), "--steps", "1")
    assert code == 2
    assert "stifness" in err and str(path) in err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("args, word", [
    (["run", "no-such-scene"], "no-such-scene"),
    (["run", "spring", "--dt", "0"], "dt"),
    (["run", "spring", "--set", "mass=-1"], "mass"),
    (["run", "spring", "--set", "stiffness=[1, 2]"], "stiffness"),
    (["run", "spring", "--set", "nonsense"], "--set"),
    (["run", "spring", "--steps", "-1"], "--steps"),
    (["run", "spring", "--out", "/nonexistent-dir/x.npz"], "--out"),
])
def test_bad_input_exit_2(args, word, capsys):
    assert main(args) == 2
    err = capsys.readouterr().err
    assert word in err and len(err.strip().splitlines()) == 1


def test_wrong_type_in_scene(tmp_path, capsys):
    path = tmp_path / "typed.toml"
    path.write_text('integrator = "implicit"\nduration = "long"\n[dt]\nexplicit = 1e-3\nsymplectic = 1e-3\n'
                    'implicit = 1e-2\n[model]\ngenerator = "spring"\n')
    assert main(["run", str(path)]) == 2
    assert "duration" in capsys.readouterr().err


def test_missing_key_in_scene(tmp_path, capsys):
    path = tmp_path / "missing.toml"
    path.write_text('integrator = "implicit"\n[dt]\nexplicit = 1e-3\n[model]\ngenerator = "spring"\n')
    assert main(["run", str(path)]) == 2
    assert "'duration'" in capsys.readouterr().err


def test_scene_dt_table_names_only_some_integrators(tmp_path, capsys):
    # integrators the [dt] table leaves out get a dt from the stability estimate
    path = tmp_path / "partial.toml"
    path.write_text('integrator = "implicit"\nduration = 0.1\n[dt]\nimplicit = 1e-2\n'
                    '[model]\ngenerator = "spring"\n')
    for integrator in ("symplectic", "rk4"):
        assert main(["run", str(path), "--integrator", integrator, "--quiet"]) == 0
        assert f"integrator  {integrator}, dt = " in capsys.readouterr().out
    assert main(["info", str(path)]) == 0
    assert "explicit" in capsys.readouterr().out


def test_unknown_arch_is_a_usage_error():
    code, out, err = run_cli("run", "spring", "--steps", "1", "--arch", "tpu")
    assert code == 2 and "--arch" in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("arch", ["cuda", "opengl", "gpu"])
def test_arch_that_cannot_start_is_a_usage_error_not_a_crash(arch):
    if os.path.exists("/dev/nvidiactl") or os.environ.get("DISPLAY"):
        pytest.skip("a GPU or a display is present: the arch may start here")
    # A fresh process: Taichi must neither fall back silently (cuda) nor crash (opengl, gpu: exit 139)
    code, out, err = run_cli("run", "spring", "--steps", "1", "--arch", arch)
    assert code == 2, (code, err)
    assert err.startswith(f"massspring: error: --arch: {arch!r} is not available here") and len(err.splitlines()) == 1
    assert "falling back" not in err and "Arch=" not in err  # Taichi's words for what massspring does not do


def test_preconditioner_option_and_scene_solver_table(tmp_path, capsys):
    path = tmp_path / "s.toml"
    path.write_text('integrator = "implicit"\nduration = 1.0\n[solver]\npreconditioner = "none"\n'
                    '[model]\ngenerator = "grid"\nresolution = 8\n')
    for extra, expected in (([], "none"), (["--preconditioner", "multigrid"], "multigrid")):
        assert main(["info", str(path), *extra]) == 0
        assert f"preconditioner {expected}" in " ".join(capsys.readouterr().out.split())
    code, out, err = run_cli("run", "cloth", "--preconditioner", "amg", "--steps", "1")
    assert code == 2 and "--preconditioner" in err and "Traceback" not in err


def test_bad_collider_exits_2_naming_it(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text('integrator = "implicit"\nduration = 1.0\n[model]\ngenerator = "chain"\ncount = 4\n'
                    '[[collider]]\ntype = "sphere"\ncenter = [0, 0, -1]\nradius = 0.0\n')
    code, out, err = run_cli("run", str(path), "--steps", "1")
    assert code == 2 and "Traceback" not in err
    assert "collider[0].radius" in err and str(path) in err


def test_set_drag_and_info_of_a_contact_scene(capsys):
    assert main(["info", "drape", "--set", "resolution=4", "--set", "drag=0.5"]) == 0
    text = capsys.readouterr().out
    terms = next(line for line in text.splitlines() if line.startswith("terms"))
    assert "drag" in terms and "contact (plane, sphere)" in terms
    assert "colliders   plane" in text and "drag 0.5" in text
    assert main(["run", "chain", "--set", "count=4", "--set", "wind=[1, 0, 0]", "--steps", "1"]) == 2
    assert "--set wind: has no effect without drag" in capsys.readouterr().err


@pytest.mark.parametrize("verb", [[], ["run"], ["info"], ["scenes"], ["stability"], ["study"]])
def test_help_is_plain_text(verb, capsys):
    with pytest.raises(SystemExit) as exit_:
        main([*verb, "--help"])
    assert exit_.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: massspring") and "``" not in out  # no reStructuredText markup
