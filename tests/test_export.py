"""run --export DIR --format obj|ply|vtk|npz: one file per frame at the GIF's frame steps, read
back by our OBJ reader, meshio and read_state; a manifest that always says how far the run got;
output directories that cannot be written refused before the first step."""

import json
import os
import sys
import time

import numpy as np
import pytest

import massspring as ms
from conftest import one_line_error
from massspring.cli import main
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
    assert sorted(p.name for p in out.iterdir()) == sorted([f["file"] for f in info["frames"]] + ["manifest.json"])
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
    obj = frames_io.WRITERS["obj"]

    def full_disk_at_the_third_frame(path, sim, scene):
        if len(written) == 2:
            raise OSError(28, "No space left on device")
        written.append(path)
        obj(path, sim, scene)

    monkeypatch.setitem(frames_io.WRITERS, "obj", full_disk_at_the_third_frame)
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


@pytest.mark.parametrize("fmt", ["ply", "vtk"])
def test_formats_that_need_meshio_say_which_extra_to_install(fmt, tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "meshio", None)  # as if it were not installed
    assert main(["run", "spring", "--steps", "5", "--quiet", "--export", str(tmp_path / "x"), "--format", fmt]) == 2
    one_line_error(capsys, f"--format {fmt}", "meshio", "massspring[mesh]")
    assert not (tmp_path / "x").exists()
