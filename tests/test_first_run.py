"""What a first user and a fuzzer hit on the command line: every failure is exit 2
(bad input) or 3 (divergence) with a one-line message and no traceback, decided before
the first step; outputs are written independently and nothing computed is lost."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import one_line_error
from massspring import __version__
from massspring.cli import main
from massspring.io.files import atomic_output


def run_cli(*args, timeout=300):
    proc = subprocess.run([sys.executable, "-m", "massspring", *args], capture_output=True, text=True,
                          timeout=timeout)
    return proc.returncode, proc.stdout, proc.stderr


@pytest.mark.parametrize("args, word", [
    (["--cg-max-iter", "4294967297"], "--cg-max-iter"),
    (["--duration", "inf"], "--duration"),
    (["--duration", "nan"], "--duration"),
    (["--duration", "1e300"], "--duration"),
    (["--dt", "inf"], "--dt"),
    (["--set", "stiffness=inf"], "stiffness"),
    (["--steps", "99999999999999999999"], "--steps"),
    (["--out", ""], "--out"),
    (["--gif", ""], "--gif"),
    (["--png", "last.gif"], "--png"),
    (["--gif", "run.png"], "--gif"),
    (["--out", "state.txt"], "--out"),
    (["--precision", "f32", "--set", "stiffness=1e30"], "stiffness"),
    (["--set", "stiffness=" + "9" * 400], "stiffness"),   # an integer beyond any float
    (["--set", "gravity=[0, 0, -" + "9" * 400 + "]"], "gravity"),
    (["--fps", "0.001", "--gif", "x.gif"], "--fps"),     # a GIF delay beyond its 16 bits
    (["--export", "x" * 300], "--export"),               # a directory name too long
    (["--set", "stiffness=5\ndamping=3"], "one value on one line"),  # the second line was ignored
])
def test_bad_values_exit_2_before_the_run(args, word, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["run", "spring", "--quiet", *args]) == 2
    one_line_error(capsys, word)
    assert not list(tmp_path.iterdir())  # nothing written, no temporary file


@pytest.mark.parametrize("args, message", [
    (["run", "cloth", "--cg-tol", "2"], "--cg-tol: must be < 1"),
    (["run", "cloth", "--set", "resolution=0"], "--set resolution: must be >= 2, got 0"),
    (["run", "cloth", "--set", "stiffness=-1"], "--set stiffness: must be >= 0, got -1"),
    (["run", "cube", "--set", "damping=-1"], "--set damping: must be >= 0, got -1"),
    (["run", "chain", "--set", "drag=0.1", "--set", "wind=[1, 0]"], "--set wind: expected 3"),
    (["run", "cloth", "--integrator", "explicit", "--preconditioner", "multigrid"],
     "--preconditioner: explicit solves no linear system"),
    (["info", "chain", "--integrator", "symplectic", "--cg-tol", "1e-3", "--no-definiteness-fix"],
     "--cg-tol/--no-definiteness-fix: symplectic solves no linear system"),
    (["run", "drape", "--duration", "0.001"], "--duration: 0.001 s is shorter than one step (dt = 1/60 s)"),
])
def test_errors_name_the_option_given_not_internal_names(args, message, capsys):
    assert main(args) == 2
    err = one_line_error(capsys, message)
    assert ".toml" not in err  # the scene file is not to blame


@pytest.mark.parametrize("settings, word", [(["seed=-5"], "seed"), (["resolution=4", "resolution=5"], "resolution")])
def test_bad_settings_name_the_key(settings, word, capsys):
    args = ["run", "cloth", "--steps", "1", "--quiet"]
    for item in settings:
        args += ["--set", item]
    assert main(args) == 2
    one_line_error(capsys, word)


def test_output_paths_checked_before_the_first_step(tmp_path, capsys):
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    cases = [("--out", str(tmp_path)),                          # an existing directory
             ("--gif", str(tmp_path / "no" / "such" / "x.gif")),  # a missing directory
             ("--png", "/proc/massspring.png"),                   # a file system that refuses files
             ("--out", str(tmp_path / ("x" * 300 + ".npz")))]     # a name too long
    if os.geteuid() != 0:  # root may write anywhere
        cases.append(("--out", str(locked / "x.npz")))
    for option, path in cases:
        start = time.perf_counter()
        assert main(["run", "cloth", "--set", "resolution=12", "--steps", "100000", "--quiet", option, path]) == 2, (option, path)
        one_line_error(capsys, option)
        assert time.perf_counter() - start < 30  # refused before 100000 steps, not after


def test_failed_picture_keeps_the_state_file(tmp_path, capsys, monkeypatch):
    from massspring.io import render

    def fail(path, frames, fps):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(render, "write_gif", fail)
    out, gif, png = tmp_path / "state.npz", tmp_path / "run.gif", tmp_path / "last.png"
    code = main(["run", "spring", "--steps", "10", "--quiet", "--out", str(out), "--gif", str(gif),
                 "--png", str(png)])
    err = capsys.readouterr().err
    assert code == 1 and "--gif" in err and "No space left" in err
    assert out.is_file() and png.is_file() and not gif.exists()
    assert int(np.load(out)["steps"]) == 10


def test_stale_temporary_file_of_a_killed_run_is_cleaned(tmp_path, capsys):
    # a process killed during the final write (SIGKILL) leaves its temporary file
    gif = tmp_path / "run.gif"
    writer = (f"import time\nfrom massspring.io.files import atomic_output\n"
              f"with atomic_output({str(gif)!r}) as fh:\n    fh.write(b'half a GIF'); fh.flush(); time.sleep(60)\n")
    proc = subprocess.Popen([sys.executable, "-c", writer])
    deadline = time.monotonic() + 60
    while not list(tmp_path.glob(".run.gif.*.tmp")) and time.monotonic() < deadline:
        time.sleep(0.05)
    proc.kill()
    proc.wait()
    [stale] = tmp_path.glob(".run.gif.*.tmp")
    with atomic_output(tmp_path / "run.png"):  # a write in progress (this process): kept
        [mine] = tmp_path.glob(".run.png.*.tmp")
        assert main(["run", "spring", "--steps", "3", "--quiet", "--gif", str(gif)]) == 0
        assert not stale.exists() and mine.exists() and gif.is_file()


@pytest.mark.full
def test_sigterm_is_handled_like_ctrl_c(tmp_path):
    """SIGTERM once the run has made 100 steps (its exported frame of step 100 is on
    disk): exit 143, no traceback, and the state file holds the state reached, at least
    those 100 steps, with the GIF of the frames recorded so far."""
    out, gif, frames = tmp_path / "state.npz", tmp_path / "run.gif", tmp_path / "frames"
    proc = subprocess.Popen([sys.executable, "-m", "massspring", "run", "cloth", "--set", "resolution=12", "--steps", "100000", "--quiet",
                             "--out", str(out), "--gif", str(gif), "--every", "50", "--export", str(frames)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and not list(frames.glob("frame_*100.obj")) and proc.poll() is None:
        time.sleep(0.05)
    assert proc.poll() is None, "the run ended before it was signalled"
    proc.send_signal(signal.SIGTERM)
    stdout, stderr = proc.communicate(timeout=300)
    assert proc.returncode == 128 + signal.SIGTERM, stderr
    assert "terminated after" in stderr and "Traceback" not in stderr
    data = np.load(out)
    assert 100 <= int(data["steps"]) < 100000 and np.all(np.isfinite(data["positions"]))
    assert f"steps       {int(data['steps'])} " in stdout  # the summary of the state reached
    assert gif.is_file()


def test_only_the_first_signal_of_a_run_raises_and_later_ones_are_recorded():
    """Issue 42: a second Ctrl-C or SIGTERM right after the first (which stops the steps)
    raised again, before the outputs were written, and the run ended without its state
    file in 1 of 8 tries. From the first signal on, the run's handler only records."""
    from massspring.cli.common import Terminated
    from massspring.cli.run import RunSignals

    before = signal.getsignal(signal.SIGINT)
    with RunSignals() as signals:
        with pytest.raises(Terminated) as info:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(5)  # the handler runs here and raises
        assert info.value.signum == signal.SIGTERM and not signals.arrived()
        os.kill(os.getpid(), signal.SIGINT)
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(0.05)  # both handled, neither raising
        assert signals.signum == signal.SIGINT and signals.arrived()
    assert signal.getsignal(signal.SIGINT) is before
    with RunSignals() as signals:
        signals.record_only()  # the steps ended without a signal: a first one while writing is recorded
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(0.05)
        assert signals.signum == signal.SIGTERM


def test_misspelt_option_prints_the_verbs_usage(capsys):
    with pytest.raises(SystemExit) as info:
        main(["run", "cloth", "--stpes", "5"])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert "usage: massspring run" in err and "--stpes" in err


def test_version(capsys):
    with pytest.raises(SystemExit) as info:
        main(["--version"])
    assert info.value.code == 0 and capsys.readouterr().out.strip() == f"massspring {__version__}"


def test_divergence_says_what_to_try(capsys):
    code = main(["run", "stiffchain", "--integrator", "symplectic", "--dt", "1e-3", "--steps", "200", "--quiet"])
    err = capsys.readouterr().err
    assert code == 3 and err.count("\n") == 1
    assert "diverged at step" in err and "--dt" in err and "--integrator implicit" in err


def test_summary_prints_round_off_as_zero(capsys):
    # the spring scene has no gravity: its gravity energy is 0, not -0 or 1e-26
    assert main(["run", "spring", "--steps", "5", "--quiet"]) == 0
    energy = next(line for line in capsys.readouterr().out.splitlines() if line.startswith("energy"))
    assert "gravity 0)" in energy and "e-2" not in energy and "-0" not in energy


@pytest.mark.full
def test_f32_kernels_compile_without_precision_warnings(tmp_path):
    """Taichi warns on every implicit f64 -> f32 conversion when it compiles a kernel
    (once per kernel, then cached): an f32 run must print none. Fresh process, cache off."""
    script = ("import massspring as ms\n"
              "scene = ms.load_scene('cloth').with_params(resolution=40)\n"
              "for integrator, pre in (('rk4', None), ('implicit', 'block-jacobi'), ('implicit', 'multigrid')):\n"
              "    sim = scene.simulation(integrator=integrator, precision='f32', preconditioner=pre,"
              " dt=1e-4 if integrator == 'rk4' else 1 / 60)\n"
              "    sim.step(2)\n"
              "    sim.close()\n"
              "for name in ('drape', 'flag'):\n"  # colliders and friction; drag and wind
              "    for integrator in ('symplectic', 'implicit'):\n"
              "        sim = ms.load_scene(name).with_params(resolution=6).simulation(integrator=integrator,"
              " precision='f32', dt=1e-4 if integrator == 'symplectic' else 1 / 60)\n"
              "        sim.step(2)\n"
              "        sim.close()\n")
    env = dict(os.environ, TI_OFFLINE_CACHE="0")
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "lose precision" not in proc.stderr and "TaichiWarning" not in proc.stderr, proc.stderr[-2000:]


@pytest.mark.parametrize("text, words", [
    ("duration = " + "9" * 400, ("duration", "beyond the range of a number", "(400 characters)")),
    ('duration = 1.0\n[[collider]]\ntype = ["plane"]', ("collider[0].type", "['plane']")),
])
def test_bad_numbers_and_types_in_scene_files(text, words, tmp_path, capsys):
    scene = tmp_path / "s.toml"
    scene.write_text('description = "x"\nintegrator = "implicit"\n' + text.replace("[[collider]]", "[model]\n"
                     'generator = "chain"\n[[collider]]') + ("" if "[model]" in text or "collider" in text
                                                             else '\n[model]\ngenerator = "chain"\n'))
    assert main(["run", str(scene), "--steps", "1", "--quiet"]) == 2
    err = one_line_error(capsys, *words)
    assert len(err) < 400  # a long bad value is cut, not echoed whole


def test_derived_counts_that_overflow_are_refused(tmp_path, capsys):
    # subnormal: 1/dt overflows (read as 0 where an earlier library set flush-to-zero)
    assert main(["run", "spring", "--dt", "1e-320", "--steps", "2", "--quiet"]) == 2
    one_line_error(capsys, "--dt")
    assert main(["info", "spring", "--dt", "1e-300"]) == 0  # normal, tiny: prints
    assert "1e-300 s" in capsys.readouterr().out
    assert main(["study", "spring", "--duration", "1e308", "--out", str(tmp_path / "st")]) == 2
    one_line_error(capsys, "duration", "steps")
    assert main(["stability", "spring", "--run-duration", "1e308", "--max-steps", "3", "--predict-only",
                 "--out", str(tmp_path / "stab")]) == 0


@pytest.mark.parametrize("argv, words", [
    (["run", "cloth", "--set", "resolution=" + "1" + "0" * 200, "--steps", "1"], ["resolution", "401-digit"]),
    (["info", "chain", "--set", "count=" + "9" * 400], ["count", "400-digit"]),
    (["run", "a" * 300, "--steps", "1"], ["scene:", "(302 characters)", "File name too long"]),
    (["stability", "spring", "--at", "1e308", "--predict-only"], ["--at", "inf steps"]),
    (["stability", "spring", "--at", "1e20", "--predict-only"], ["--at", "1e+22 steps"]),
    (["sweep", "spring", "--duration", "1e308", "--vary", "stiffness=1,2", "--yes"], ["--duration", "case 1"]),
    (["run", "spring", "--size", "x" * 100_000, "--png", "a.png"], ["--size", "characters"]),
    (["run", "spring", "--integrator", "x" * 100_000], ["--integrator", "characters"]),
])
def test_oversized_inputs_are_one_short_line(argv, words, tmp_path, monkeypatch, capsys):
    """Sizes beyond any float, names longer than a file system takes, durations of more
    steps than a run may have and 100 KB arguments: exit 2 before any step, on one line
    of at most about 1,000 characters naming the input."""
    monkeypatch.chdir(tmp_path)
    if argv[0] == "sweep":
        argv = argv + ["--out", str(tmp_path / "s.csv")]
    try:
        code = main(argv)
        err = one_line_error(capsys, *words)
    except SystemExit as exc:  # argparse's own errors: its usage, then one line
        code = exc.code
        err = capsys.readouterr().err
        assert "Traceback" not in err and all(word in err.splitlines()[-1] for word in words), err
        err = err.splitlines()[-1]
    assert code == 2 and len(err) <= 1100
    assert not (tmp_path / "s.csv").exists()


def test_a_nul_byte_in_a_message_is_escaped(tmp_path, capsys):
    scene = tmp_path / "nul.toml"
    scene.write_text('integrator = "implicit"\nduration = 1.0\n[model]\nmesh = "a\\u0000b.obj"\n')
    assert main(["run", str(scene)]) == 2
    err = one_line_error(capsys, "model.mesh", "a\\x00b.obj")
    assert "\x00" not in err


def test_a_scene_file_beyond_the_size_limit_is_not_read(tmp_path, capsys):
    from massspring.scene.spec import MAX_SCENE_BYTES

    scene = tmp_path / "big.toml"
    with open(scene, "wb") as fh:
        fh.write(b'integrator = "implicit"\nduration = 1.0\n# ' + b"x" * MAX_SCENE_BYTES + b"\n")
    assert main(["run", str(scene)]) == 2
    one_line_error(capsys, "big.toml", "more than 64 MB")


def test_taichi_that_cannot_start_is_a_clear_error():
    """Under an address-space limit too small for Taichi's memory pool (about 1.6 GB
    reserved), starting it fails: exit 2 naming --arch, not Taichi's RuntimeError. On a
    machine where the run fits it exits 0; never a traceback."""
    import resource

    def limit():
        resource.setrlimit(resource.RLIMIT_AS, (1_600_000_000, 1_600_000_000))

    proc = subprocess.run([sys.executable, "-m", "massspring", "run", "spring", "--steps", "1", "--quiet"],
                          capture_output=True, text=True, timeout=300, preexec_fn=limit)
    assert "Traceback" not in proc.stderr, proc.stderr
    assert proc.returncode in (0, 2), proc.stderr
    if proc.returncode == 2:
        assert proc.stderr.startswith("massspring: error: ") and proc.stderr.count("\n") == 1, proc.stderr


def test_a_diverging_settling_run_of_stability_at_is_exit_3(tmp_path, capsys):
    """``stability --at`` first runs the scene's implicit step; at dt = 1 s the chain
    diverges at step 4 (the state grows past the energy bound): one line naming --at,
    exit 3, no traceback."""
    scene = tmp_path / "c.toml"
    scene.write_text((Path(__file__).parents[1] / "scenes" / "chain.toml").read_text()
                     .replace("implicit = 0.01", "implicit = 1.0"))
    assert main(["stability", str(scene), "--at", "20", "--predict-only"]) == 3
    one_line_error(capsys, "--at 20 s: the settling run: implicit diverged at step 4", "runaway growth")


def test_ctrl_c_outside_a_run_is_exit_130_without_a_traceback(monkeypatch, capsys):
    from massspring import cli

    def interrupted(args):
        raise KeyboardInterrupt

    monkeypatch.setitem(cli.COMMANDS, "scenes", interrupted)
    assert main(["scenes"]) == 130
    one_line_error(capsys, "massspring: interrupted")
