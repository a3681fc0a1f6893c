"""run --export DIR --format obj|ply|vtk|npz|usd: one file per frame at the GIF's frame steps
(usd: one stage for the run), read back by our OBJ reader, meshio, read_state and pxr; a
manifest that always says how far the run got; output directories that cannot be written
refused before the first step."""

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

import massspring as ms
from conftest import FULL, one_line_error
from massspring.cli import main
from massspring.support.extras import install_hint
from massspring.io import frames as frames_io
from massspring.io.obj import read_obj
from massspring.io.render import frame_steps
from massspring.io.state import read_state

CLOTH = ["cloth", "--set", "resolution=5", "--quiet"]


def manifest(directory):
    return json.loads((directory / "manifest.json").read_text())


def test_obj_frames_at_the_gif_steps_read_back_exactly(tmp_path, capsys):
    out, state = tmp_path / "frames", tmp_path / "last.npz"
    assert main(["run", *CLOTH, "--steps", "12", "--every", "5", "--export", str(out), "--out", str(state)]) == 0
    assert "wrote 4 obj frame(s)" in capsys.readouterr().out
    steps = frame_steps(12, every=5).tolist()
    assert steps == [0, 5, 10, 12]
    info = manifest(out)
    assert [f["step"] for f in info["frames"]] == steps
    assert [f["time"] for f in info["frames"]] == pytest.approx([s / 60 for s in steps], rel=1e-12)
    assert sorted(p.name for p in out.iterdir()) == sorted([f["file"] for f in info["frames"]]
                                                           + ["manifest.json", "frames.jsonl"])
    assert [json.loads(line) for line in (out / "frames.jsonl").read_text().splitlines()] == info["frames"]
    assert info["status"] == "complete" and info["last_step"] == 12 and info["format"] == "obj"
    assert info["integrator"] == "implicit" and info["dt"] == pytest.approx(1 / 60) and info["series"] is None
    assert info["scene"]["name"] == "cloth" and info["scene"]["params"]["resolution"] == 5
    assert info["particles"] == 25 and info["triangles"] == 32
    model = ms.load_scene("cloth").with_params(resolution=5).model()
    first, last = read_obj(out / info["frames"][0]["file"]), read_obj(out / info["frames"][-1]["file"])
    assert np.array_equal(first.vertices, model.positions) and first.faces == model.triangles.tolist()
    assert np.array_equal(last.vertices, np.load(state)["positions"])  # float64, to the bit


def test_frames_option_spreads_frames_over_the_run(tmp_path):
    out = tmp_path / "frames"
    assert main(["run", *CLOTH, "--steps", "9", "--frames", "4", "--export", str(out), "--format", "npz"]) == 0
    info = manifest(out)
    assert [f["step"] for f in info["frames"]] == frame_steps(9, frames=4).tolist() == [0, 3, 6, 9]
    last = read_state(out / info["frames"][-1]["file"])  # an npz frame is a state file
    assert last.steps == 9 and last.scene == "cloth"


def test_ply_and_vtk_frames_are_read_back_by_meshio(tmp_path):
    meshio = pytest.importorskip("meshio")
    states = tmp_path / "npz"
    assert main(["run", *CLOTH, "--steps", "6", "--every", "3", "--export", str(states), "--format", "npz"]) == 0
    expected = [read_state(states / f["file"]) for f in manifest(states)["frames"]]
    model = ms.load_scene("cloth").with_params(resolution=5).model()
    for fmt, ext in (("ply", ".ply"), ("vtk", ".vtu")):
        out = tmp_path / fmt
        assert main(["run", *CLOTH, "--steps", "6", "--every", "3", "--export", str(out), "--format", fmt]) == 0
        info = manifest(out)
        assert len(info["frames"]) == 3 and all(f["file"].endswith(ext) for f in info["frames"])
        for frame, state in zip(info["frames"], expected):
            mesh = meshio.read(out / frame["file"])
            assert np.array_equal(mesh.points, state.positions)
            assert np.array_equal(mesh.cells_dict["triangle"], model.triangles)
            if fmt == "vtk":
                assert np.array_equal(mesh.point_data["velocity"], state.velocities)
    series = (tmp_path / "vtk" / "frames.pvd").read_text()
    assert manifest(tmp_path / "vtk")["series"] == "frames.pvd"
    for frame in manifest(tmp_path / "vtk")["frames"]:
        assert f'timestep="{frame["time"]!r}" group="" part="0" file="{frame["file"]}"' in series


def test_model_without_a_surface_exports_its_springs_as_lines(tmp_path):
    out = tmp_path / "chain"
    assert main(["run", "chain", "--set", "count=6", "--steps", "4", "--frames", "2", "--quiet",
                 "--export", str(out)]) == 0
    text = (out / "frame_00001.obj").read_text().splitlines()
    assert sum(line.startswith("v ") for line in text) == 6 and sum(line.startswith("l ") for line in text) == 5


def test_divergence_keeps_the_frames_and_the_manifest_says_where_it_stopped(tmp_path, capsys):
    out = tmp_path / "frames"
    code = main(["run", "stiffchain", "--integrator", "symplectic", "--dt", "1e-3", "--steps", "200", "--every",
                 "5", "--quiet", "--export", str(out)])
    assert code == 3
    info = manifest(out)
    assert info["status"] == "diverged" and "diverged at step" in info["message"]
    stopped = info["last_step"]
    assert 0 < stopped < 200 and info["frames"][-1]["step"] == stopped - stopped % 5
    assert [f["step"] for f in info["frames"]] == list(range(0, stopped + 1, 5))
    assert all((out / f["file"]).is_file() for f in info["frames"])
    assert f"the run stopped at step {stopped} of 200" in capsys.readouterr().err


def test_an_error_controlled_run_says_in_time_where_it_stopped(tmp_path, capsys):
    """A run with --tol counts no steps ahead: run to its end its pictures are written
    as complete; stopped (steps held at a min_dt above symplectic Euler's limit on the
    stiff chain: StepSizeError) the CLI names the time it reached of the time asked."""
    png, out = tmp_path / "end.png", tmp_path / "frames"
    assert main(["run", "stiffchain", "--integrator", "symplectic", "--tol", "1e-2", "--duration", "2e-3",
                 "--png", str(png)]) == 0
    captured = capsys.readouterr()
    assert "pictures    wrote" in captured.out and "stopped" not in captured.err and png.is_file()
    assert main(["run", "stiffchain", "--integrator", "symplectic", "--tol", "1e-2", "--duration", "0.05",
                 "--min-dt", "1e-3", "--max-dt", "1e-3", "--quiet", "--png", str(png), "--export", str(out)]) == 3
    err = capsys.readouterr().err
    assert err.count("massspring: the run stopped at t = ") == 2 and err.count(" s of 0.05 s; wrote ") == 2, err
    assert manifest(out)["status"] == "diverged"


def test_interrupted_run_keeps_its_frames(tmp_path, capsys, monkeypatch):
    calls = []
    step = ms.Simulation.step

    def interrupt_on_the_third_call(self, n=1):
        calls.append(n)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return step(self, n)

    monkeypatch.setattr(ms.Simulation, "step", interrupt_on_the_third_call)
    out = tmp_path / "frames"
    assert main(["run", *CLOTH, "--steps", "20", "--every", "2", "--export", str(out)]) == 130
    info = manifest(out)
    assert info["status"] == "interrupted" and info["last_step"] == 2  # run() steps 1 at a time here
    assert [f["step"] for f in info["frames"]] == [0, 2]


def test_a_frame_that_cannot_be_written_stops_the_export_not_the_run(tmp_path, capsys, monkeypatch):
    written = []
    obj = frames_io.write_obj_frame

    def full_disk_at_the_third_frame(path, sim, scene):
        if len(written) == 2:
            raise OSError(28, "No space left on device")
        written.append(path)
        obj(path, sim, scene)

    monkeypatch.setattr(frames_io, "write_obj_frame", full_disk_at_the_third_frame)
    out, state = tmp_path / "frames", tmp_path / "state.npz"
    assert main(["run", *CLOTH, "--steps", "10", "--every", "2", "--export", str(out), "--out", str(state)]) == 1
    err = capsys.readouterr().err
    assert "--export" in err and "No space left" in err
    info = manifest(out)
    assert info["status"] == "failed" and "No space left" in info["message"] and len(info["frames"]) == 2
    assert int(np.load(state)["steps"]) == 10  # the run went on


def test_output_directories_that_cannot_be_written_are_refused_before_the_run(tmp_path, capsys):
    a_file = tmp_path / "file"
    a_file.write_text("")
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    cases = [(str(a_file), "is not a directory"), ("/proc/massspring-frames", "--export"),
             (str(a_file / "below"), "--export")]
    if os.geteuid() != 0:  # root may write anywhere
        cases += [(str(locked), "locked"), (str(locked / "new"), "cannot create")]
    for path, word in cases:
        start = time.perf_counter()
        assert main(["run", "cloth", "--steps", "100000", "--quiet", "--export", path]) == 2, path
        one_line_error(capsys, "--export", word)
        assert time.perf_counter() - start < 30  # refused before 100000 steps, not after
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file", "locked"] and not list(locked.iterdir())


@pytest.mark.parametrize("args, words", [
    (["--format", "obj"], ["--format", "only with --export"]),
    (["--export", "X", "--size", "100x100"], ["--size", "only with --gif or --png"]),
    (["--frames", "3"], ["--frames", "only with --gif, --png or --export"]),
    (["--export", "X", "--frames", "99"], ["--frames", "within 1..11"]),
    (["--export", ""], ["--export", "empty path"]),
])
def test_bad_export_options_exit_2(args, words, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["run", "spring", "--steps", "10", "--quiet", *args]) == 2
    one_line_error(capsys, *words)
    assert not list(tmp_path.iterdir())


def test_export_alone_takes_frames_and_every(tmp_path):
    out = tmp_path / "frames"
    assert main(["run", "spring", "--steps", "10", "--quiet", "--export", str(out), "--every", "4"]) == 0
    assert [f["step"] for f in manifest(out)["frames"]] == [0, 4, 8, 10]


@pytest.mark.parametrize("fmt, module, extra", [("ply", "meshio", "mesh"), ("vtk", "meshio", "mesh"),
                                               ("usd", "pxr", "usd")])
def test_formats_that_need_a_module_say_which_extra_to_install(fmt, module, extra, tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, module, None)  # as if it were not installed
    assert main(["run", "spring", "--steps", "5", "--quiet", "--export", str(tmp_path / "x"), "--format", fmt]) == 2
    one_line_error(capsys, f"--format {fmt}", module, install_hint(extra))  # the extra's own packages
    assert not (tmp_path / "x").exists()


def test_every_format_is_one_record_and_its_extra_installs_its_module():
    import tomllib
    from pathlib import Path

    extras = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())
    extras = extras["project"]["optional-dependencies"]
    packages = {"meshio": "meshio", "pxr": "usd-core"}  # module -> the package that installs it
    for name, record in frames_io.FORMATS.items():
        assert record.name == name and record.extension.startswith(".")
        assert callable(record.load())  # the writer exists
        if record.module is not None:
            assert any(r.startswith(packages[record.module]) for r in extras[record.extra]), name
            assert any(r.startswith(packages[record.module]) for r in extras["test"]), name  # CI tests it
    parser, _ = cli_parser()
    help_text = " ".join(parser.format_help().split())
    for record in frames_io.FORMATS.values():
        assert f"{record.name}: {record.help}" in help_text


def cli_parser():
    from massspring import cli

    parser, verbs = cli.build_parser()
    return verbs["run"], verbs


# ----------------------------------------------------------------------------- USD


def usd_stage(path):
    pytest.importorskip("pxr", reason="usd-core is not installed (pip install -e '.[usd]')")
    from pxr import Usd

    stage = Usd.Stage.Open(str(path))
    assert stage is not None
    return stage


@FULL
def test_usd_stage_of_drape_has_the_npz_frames_points(tmp_path):
    """drape at its default size, 60 frames: the stage's time-sampled points and
    velocities equal the npz frames' to float32 round-off, and it holds the colliders."""
    usd, npz = tmp_path / "usd", tmp_path / "npz"
    for out, fmt in ((usd, "usd"), (npz, "npz")):
        assert main(["run", "drape", "--quiet", "--steps", "59", "--every", "1", "--export", str(out),
                     "--format", fmt]) == 0
    stage = usd_stage(usd / "frames.usdc")
    info = manifest(usd)
    assert info["status"] == "complete" and info["series"] == "frames.usdc" and len(info["frames"]) == 60
    assert [f["step"] for f in info["frames"]] == [f["step"] for f in manifest(npz)["frames"]] == list(range(60))
    from pxr import UsdGeom

    scene = ms.load_scene("drape")
    model = scene.model()
    assert UsdGeom.GetStageUpAxis(stage) == "Z" and UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert stage.GetTimeCodesPerSecond() == pytest.approx(1 / scene.default_dt(), rel=1e-12)
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0, 59)
    body = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Body"))
    assert np.array_equal(np.array(body.GetFaceVertexIndicesAttr().Get()), model.triangles.ravel())
    assert body.GetPointsAttr().GetTimeSamples() == list(range(60))
    scale = np.abs(model.positions).max()
    for frame in manifest(npz)["frames"]:
        state = np.load(npz / frame["file"])
        points = np.array(body.GetPointsAttr().Get(frame["step"]), dtype=np.float64)
        velocities = np.array(body.GetVelocitiesAttr().Get(frame["step"]), dtype=np.float64)
        np.testing.assert_allclose(points, state["positions"], rtol=0, atol=2 ** -23 * scale)
        np.testing.assert_allclose(velocities, state["velocities"], rtol=2 ** -23,
                                   atol=2 ** -23 * np.abs(state["velocities"]).max())
    plane, sphere = model.colliders
    ground = UsdGeom.Plane(stage.GetPrimAtPath("/World/Colliders/plane_0"))
    ball = UsdGeom.Sphere(stage.GetPrimAtPath("/World/Colliders/sphere_1"))
    assert ball.GetRadiusAttr().Get() == sphere.radius
    world = ball.ComputeLocalToWorldTransform(0)
    assert np.allclose(world.ExtractTranslation(), sphere.center)
    transform = ground.ComputeLocalToWorldTransform(0)
    assert np.allclose(transform.ExtractTranslation(), plane.point)
    assert np.allclose(transform.TransformDir((0.0, 0.0, 1.0)), plane.normal, atol=1e-6)  # its +z is the normal


def test_usd_stage_of_a_chain_with_a_moving_box(tmp_path):
    """A model without a surface: its particles as Points, its springs as two-point
    curves; a moving collider's translation sampled at every frame."""
    path = tmp_path / "chain.toml"
    path.write_text('integrator = "symplectic"\nduration = 0.1\n[dt]\nsymplectic = 1e-3\n'
                    '[model]\ngenerator = "chain"\ncount = 4\n'
                    '[[collider]]\ntype = "box"\nlower = [0, -1, -3]\nupper = [1, 1, -2]\nvelocity = [0, 0, 2]\n')
    out, npz = tmp_path / "usd", tmp_path / "npz"
    for directory, fmt in ((out, "usd"), (npz, "npz")):
        assert main(["run", str(path), "--quiet", "--every", "20", "--export", str(directory), "--format", fmt]) == 0
    stage = usd_stage(out / "frames.usdc")
    from pxr import UsdGeom

    model = ms.load_scene(path).model()
    body = UsdGeom.Points(stage.GetPrimAtPath("/World/Body"))
    curves = UsdGeom.BasisCurves(stage.GetPrimAtPath("/World/Springs"))
    box = UsdGeom.Cube(stage.GetPrimAtPath("/World/Colliders/box_0"))
    assert curves.GetCurveVertexCountsAttr().Get() == [2] * model.n_springs
    steps = [f["step"] for f in manifest(npz)["frames"]]
    assert steps == [0, 20, 40, 60, 80, 100] and body.GetPointsAttr().GetTimeSamples() == steps
    for frame in manifest(npz)["frames"]:
        x = np.load(npz / frame["file"])["positions"]
        points = np.array(body.GetPointsAttr().Get(frame["step"]), dtype=np.float64)
        np.testing.assert_allclose(points, x, rtol=0, atol=2 ** -23 * np.abs(x).max())
        ends = np.array(curves.GetPointsAttr().Get(frame["step"]), dtype=np.float64).reshape(-1, 2, 3)
        np.testing.assert_allclose(ends, x[model.springs], rtol=0, atol=2 ** -23 * np.abs(x).max())
        moved = model.colliders[0].at(frame["time"])
        world = box.ComputeLocalToWorldTransform(frame["step"])
        assert np.allclose(world.ExtractTranslation(), (np.array(moved.lower) + np.array(moved.upper)) / 2)
        assert np.allclose(world.TransformDir((1.0, 1.0, 1.0)), [1.0, 2.0, 1.0])  # scaled to its sides


@FULL
def test_usd_stage_of_a_run_that_stops_early_or_cannot_be_saved(tmp_path, capsys, monkeypatch):
    pytest.importorskip("pxr", reason="usd-core is not installed (pip install -e '.[usd]')")
    from massspring.io import usd

    # diverges (explicit Euler on an undamped spring at dt = 0.5 s): the stage holds the frames up to then
    out = tmp_path / "boom"
    assert main(["run", "spring", "--integrator", "explicit", "--dt", "0.5", "--set", "damping=0", "--steps", "60",
                 "--every", "1", "--quiet", "--export", str(out), "--format", "usd"]) == 3
    info = manifest(out)
    steps = [f["step"] for f in info["frames"]]
    assert info["status"] == "diverged" and steps == list(range(info["last_step"] + 1))
    stage = usd_stage(out / "frames.usdc")
    assert stage.GetPrimAtPath("/World/Body").GetAttribute("points").GetTimeSamples() == steps
    # a stage that cannot be written: the run's outputs fail (exit 1), the manifest says so, no file is left
    def full_disk(self):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(usd.StageWriter, "save", full_disk)
    out = tmp_path / "full"
    assert main(["run", *CLOTH, "--steps", "4", "--export", str(out), "--format", "usd"]) == 1
    assert "No space left" in capsys.readouterr().err
    info = manifest(out)
    assert info["status"] == "failed" and info["frames"] == [] and sorted(p.name for p in out.iterdir()) == [
        "manifest.json"]


def test_the_manifest_is_rewritten_a_logarithmic_number_of_times(tmp_path, monkeypatch):
    """Each frame appends one journal line; the whole manifest is rewritten at the start,
    at frame counts that are powers of two and at the end: 12 times for 1,001 frames."""
    from massspring.io import frames

    writes = []
    original = frames.FrameExport._write_manifest
    monkeypatch.setattr(frames.FrameExport, "_write_manifest",
                        lambda self, *a: (writes.append(len(self.frames)), original(self, *a))[1])
    out = tmp_path / "e"
    assert main(["run", "spring", "--steps", "1000", "--every", "1", "--quiet", "--export", str(out)]) == 0
    assert writes == [0, 1, 2, 4, 8, 16, 32, 64, 128, 256, 512, 1001]
    info = manifest(out)
    assert [json.loads(line) for line in (out / "frames.jsonl").read_text().splitlines()] == info["frames"]
    assert len(info["frames"]) == 1001


def test_a_huge_frame_plan_starts_at_once_and_a_signal_leaves_the_frames_listed(tmp_path):
    """10^12 steps, a frame each: nothing is planned ahead (the run starts at once), and
    SIGTERM leaves a manifest listing exactly the frames on disk."""
    out = tmp_path / "e"
    proc = subprocess.Popen([sys.executable, "-m", "massspring", "run", "spring", "--steps", str(10 ** 12), "--every",
                             "1", "--quiet", "--export", str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not (out / "frame_0000000000100.obj").exists():
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 143 and "Traceback" not in err, err
    info = manifest(out)
    on_disk = sorted(p.name for p in out.glob("frame_*.obj"))
    assert info["status"] == "terminated" and len(on_disk) > 100
    assert [f["file"] for f in info["frames"]] == on_disk
    assert [json.loads(line) for line in (out / "frames.jsonl").read_text().splitlines()] == info["frames"]


@FULL
def test_a_second_signal_during_the_pictures_keeps_what_was_rendered(tmp_path):
    """SIGTERM stops the run; a second one while thousands of recorded frames are being
    rendered stops the rendering: the GIF holds the frames rendered so far, the manifest
    says "terminated", exit 143, no traceback."""
    from PIL import Image

    out, gif = tmp_path / "e", tmp_path / "a.gif"
    proc = subprocess.Popen([sys.executable, "-m", "massspring", "run", "cloth", "--set", "resolution=8", "--integrator",
                             "symplectic", "--steps", "4000000", "--every", "20", "--gif", str(gif), "--export",
                             str(out), "--quiet"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and len(list(out.glob("frame_*.obj"))) < 2000:
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    time.sleep(1.0)  # rendering 2,000 frames takes about 25 s here
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 143 and "Traceback" not in err, err
    assert "rendering interrupted" in err
    frames = Image.open(gif).n_frames
    assert 1 <= frames < len(manifest(out)["frames"])
    assert manifest(out)["status"] == "terminated"


def first_line(path):
    try:
        with open(path) as fh:
            return fh.readline()
    except FileNotFoundError:  # replaced between the check and the read
        return ""


class _Killed(BaseException):
    """Stands for SIGKILL: nothing after it runs, ``finish`` included."""


@pytest.mark.parametrize("phase", ["before the rename", "after the rename"])
@pytest.mark.parametrize("killed_at", [0, 3])
def test_read_frames_lists_exactly_this_runs_frames_after_a_kill(tmp_path, monkeypatch, phase, killed_at):
    """An earlier run left frames 0-5 of the same names; a second export is "killed"
    while writing frame ``killed_at`` (before or after its file is renamed into place,
    ``finish`` never called): read_frames lists exactly the files this run wrote, the
    earlier run's frame of that name is never taken for this run's."""
    out = tmp_path / "e"
    assert main(["run", "spring", "--steps", "5", "--every", "1", "--quiet", "--export", str(out)]) == 0
    sim = ms.load_scene("chain").with_params(count=4).simulation(integrator="symplectic")
    real = frames_io.write_obj_frame

    def writer(path, sim, scene):
        if sim.steps == killed_at and phase == "before the rename":
            raise _Killed
        real(path, sim, scene)
        if sim.steps == killed_at:
            raise _Killed

    monkeypatch.setattr(frames_io, "write_obj_frame", writer)
    export = frames_io.FrameExport(out, "obj", count=6, scene="second")
    export.prepare()
    with pytest.raises(_Killed):
        for _ in range(6):
            export(sim)
            sim.step()
    listed = frames_io.read_frames(out)
    ours = sorted(p.name for p in out.glob("frame_*.obj") if "massspring second" in first_line(p))
    written = killed_at + (phase == "after the rename")
    assert [f["file"] for f in listed] == ours == [f"frame_{k:05d}.obj" for k in range(written)]
    assert [f["step"] for f in listed] == list(range(written))
    sim.close()


@FULL
def test_read_frames_after_sigkill_of_a_real_run(tmp_path):
    """SIGKILL at three moments of a run exporting every step into a directory an earlier
    run filled with frames of the same names: read_frames lists exactly the frames the
    killed run wrote (its scene is in each file's first line), in order from frame 0."""
    out = tmp_path / "e"
    command = [sys.executable, "-m", "massspring", "run", "{scene}", "--steps", str(10 ** 12), "--every", "1",
               "--quiet", "--export", str(out)]

    def start(scene):
        return subprocess.Popen([a.format(scene=scene) for a in command], stdout=subprocess.DEVNULL,
                                stderr=subprocess.PIPE, text=True)

    def wait_for(frame, scene):
        path, deadline = out / f"frame_{frame:013d}.obj", time.monotonic() + 60
        while time.monotonic() < deadline and not (path.exists() and f"massspring {scene}" in first_line(path)):
            time.sleep(0.01)

    first = start("spring")
    wait_for(400, "spring")
    first.send_signal(signal.SIGTERM)
    assert first.wait(timeout=60) == 143
    for delay in (0.0, 0.013, 0.029):
        proc = start("chain")
        wait_for(100, "chain")
        time.sleep(delay)
        proc.kill()
        proc.wait(timeout=60)
        listed = [f["file"] for f in frames_io.read_frames(out)]
        ours = sorted(p.name for p in out.glob("frame_*.obj") if "massspring chain" in first_line(p))
        assert listed == ours == [f"frame_{k:013d}.obj" for k in range(len(ours))] and len(ours) >= 100


def test_read_frames_names_a_directory_that_is_no_export(tmp_path):
    with pytest.raises(ValueError, match="manifest.json.*not the manifest of an export"):
        frames_io.read_frames(tmp_path)


@pytest.mark.parametrize("manifest, words", [
    ({"status": "complete", "journal": None, "frames": [{"file": "/etc/passwd", "step": 0, "time": 0.0}]},
     "'/etc/passwd' is not a file name inside"),
    ({"status": "complete", "journal": None, "frames": [{"file": "../x.obj", "step": 0, "time": 0.0}]},
     "'../x.obj' is not a file name inside"),
    ({"status": "running", "journal": "/etc/passwd", "frames": []}, "'/etc/passwd' is not a file name inside"),
    ({"status": "complete", "journal": None, "frames": {"file": "a"}}, "frames: expected a list, got dict"),
    ({"status": "complete", "journal": None, "frames": ["frame_00000.obj"]}, "expected {file, step, time}"),
    ({"status": "complete", "journal": None, "frames": [{"file": "a.obj", "step": "0", "time": 0}]},
     "step and time must be numbers"),
])
def test_read_frames_refuses_a_crafted_manifest(tmp_path, manifest, words):
    """Issue 42: a crafted manifest made ``read_frames`` return absolute paths
    (/etc/passwd) or non-lists; it now names the manifest and what is wrong."""
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ValueError, match="not the manifest of an export") as info:
        frames_io.read_frames(tmp_path)
    assert words in str(info.value)


def test_read_frames_reads_regular_bounded_files_only(tmp_path, monkeypatch):
    """Issue 42: a FIFO manifest hung ``read_frames``, /dev/zero or an 8 GB sparse one
    was read whole, and nested JSON raised RecursionError."""
    fifo = tmp_path / "fifo"
    fifo.mkdir()
    os.mkfifo(fifo / "manifest.json")
    with pytest.raises(ValueError, match="not a regular file"):
        frames_io.read_frames(fifo)
    nested = tmp_path / "nested"
    nested.mkdir()
    (nested / "manifest.json").write_text("[" * 100000 + "]" * 100000)
    with pytest.raises(ValueError, match="not the manifest of an export"):
        frames_io.read_frames(nested)
    monkeypatch.setattr(frames_io, "MAX_LIST_BYTES", 1000)
    big = tmp_path / "big"
    big.mkdir()
    with open(big / "manifest.json", "wb") as fh:
        fh.truncate(8 * 2**30)  # sparse: 8 GB that take no disk
    with pytest.raises(ValueError, match="more than 0 MB"):
        frames_io.read_frames(big)
