"""Runs too large for the memory this process may take are refused before the model is
built: quickly, with exit 2 and one line naming the size, under any of the limits
(memory available, cgroup, ``ulimit -v``). Every test that probes a large size runs it
under an address-space limit, so a regression fails the test instead of the machine."""

import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import pytest

import massspring as ms
from conftest import one_line_error
from massspring.support import memory
from massspring.cli import main
from massspring.scene import generators

GB = 1e9
# Address space of a test's child process: Taichi reserves about 1.7 GB at start, so
# this leaves about 2 GB for what a run allocates.
CHILD_AS_KB = 4_000_000


# Runs the CLI in a child under an address-space limit and prints the child's own peak
# RSS (VmHWM, kB) on the last line of stdout: ru_maxrss of a forked child starts from
# the parent's, so it cannot tell what the child itself took.
LIMITED = """
import resource, sys
limit = int(sys.argv[1]) * 1024
resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
from massspring.cli import main
try:
    code = main(sys.argv[2:])
finally:
    print([line.split()[1] for line in open("/proc/self/status") if line.startswith("VmHWM:")][0], flush=True)
sys.exit(code)
"""


def run_limited(*args, as_kb=CHILD_AS_KB, timeout=120):
    """``massspring ARGS`` under ``ulimit -v as_kb``: (exit code, stderr, wall s, the
    child's peak RSS in bytes)."""
    start = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", LIMITED, str(as_kb), *args], capture_output=True, text=True,
                          timeout=timeout)
    peak = int(proc.stdout.strip().splitlines()[-1]) * 1024
    return proc.returncode, proc.stderr, time.perf_counter() - start, peak


@pytest.mark.parametrize("resolution", [1000, 3000, 5000])
def test_too_large_under_ulimit_is_refused_at_once(resolution):
    code, err, wall, peak = run_limited("run", "cloth", "--set", f"resolution={resolution}", "--steps", "1", "--quiet")
    assert code == 2, err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert f"resolution = {resolution} gives {resolution ** 2:,} particles" in err
    assert "GB" in err and "ulimit -v" in err
    assert wall < 30  # refused before building: about 0.6 s here; building 1000^2 alone takes longer
    assert peak < 500e6  # about 100 MB: the interpreter, numpy and Taichi's runtime


def test_a_run_that_fits_under_ulimit_runs():
    code, err, _, _ = run_limited("run", "cloth", "--set", "resolution=40", "--steps", "2", "--quiet")
    assert code == 0, err


def test_memory_available_is_checked_before_building(monkeypatch, capsys):
    monkeypatch.setattr(memory, "_mem_available", lambda: 8 * GB)
    monkeypatch.setattr(memory, "_cgroup_room", lambda: None)
    monkeypatch.setattr(memory, "_address_space_room", lambda: None)

    def never(**kw):
        raise AssertionError("the model was built")

    monkeypatch.setitem(generators.GENERATORS, "grid", never)
    monkeypatch.setattr(generators, "grid", never)
    for args in (["run", "cloth", "--set", "resolution=5000", "--steps", "1", "--quiet"],
                 ["info", "cloth", "--set", "resolution=2000"],
                 ["run", "cloth", "--set", "resolution=2000", "--integrator", "explicit", "--steps", "1", "--quiet"]):
        assert main(args) == 2
        one_line_error(capsys, "GB", "of memory available", "resolution = ")


def test_the_least_limit_counts(monkeypatch):
    monkeypatch.setattr(memory, "_mem_available", lambda: 20 * GB)
    monkeypatch.setattr(memory, "_address_space_room", lambda: None)
    files = {"/sys/fs/cgroup/memory.max": "6000000000", "/sys/fs/cgroup/memory.current": "1000000000"}
    monkeypatch.setattr(memory, "_read", files.get)
    assert memory.available() == (5 * GB, "left under the cgroup's memory limit")
    files["/sys/fs/cgroup/memory.max"] = "max"  # no cgroup limit
    assert memory.available() == (20 * GB, "of memory available")
    monkeypatch.setattr(memory, "_address_space_room", lambda: 3 * GB)
    assert memory.available() == (3 * GB, "of address space left under ulimit -v")
    with pytest.raises(memory.MemoryNeedError, match=r"x needs about 4 GB; 3 GB of address space left under ulimit -v"):
        memory.check(4 * GB, "x")
    memory.check(2.9 * GB, "x")


def test_simulation_of_a_model_is_refused_before_allocating(monkeypatch):
    model = ms.load_scene("cloth").with_params(resolution=6).model()
    monkeypatch.setattr(memory, "_mem_available", lambda: 1e6)
    with pytest.raises(ValueError, match=r"model: 36 particles and .* springs; a run of it \(implicit\) needs about"):
        ms.Simulation(model, integrator="implicit")


def test_hand_made_and_mesh_scenes_know_their_counts():
    hand = ms.load_scene(Path(__file__).parent.parent / "examples" / "hand_made.toml")
    model = hand.model()
    assert hand.counts() == (model.n_particles, model.n_springs)
    cloth = ms.load_scene("cloth").with_params(resolution=7)
    model = cloth.model()
    assert cloth.counts() == (model.n_particles, model.n_springs)


MEASURE = """
import json, sys
import massspring as ms

def peak():  # this process's own peak RSS in bytes (ru_maxrss would start from the parent's)
    return [int(line.split()[1]) * 1024 for line in open("/proc/self/status") if line.startswith("VmHWM:")][0]

integrator, preconditioner = sys.argv[1], sys.argv[2]
warm = ms.load_scene("spring").simulation(integrator=integrator); warm.step(); warm.close()
base = peak()
scene = ms.load_scene("cloth").with_params(resolution=110)
options = {} if preconditioner == "-" else {"preconditioner": preconditioner}
sim = scene.simulation(integrator, **options); sim.step()
print(json.dumps(peak() - base))
"""


@pytest.mark.fast_sample(integrator=["explicit"])
@pytest.mark.parametrize("integrator, preconditioner", [("explicit", "-"), ("implicit", "multigrid")])
def test_estimate_bounds_the_measured_peak(integrator, preconditioner):
    """What a 110 x 110 cloth run adds to a warm process stays under ``run_bytes``, and the
    estimate's per-item part is not more than 4x what was measured (it is fitted to it)."""
    out = subprocess.run([sys.executable, "-c", MEASURE, integrator, preconditioner], capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    added = json.loads(out.stdout.strip().splitlines()[-1])
    particles, springs = generators.counts("grid", dict(resolution=110, shear=1.0, bend=0.1))
    solver = None if preconditioner == "-" else preconditioner
    estimate = memory.run_bytes(particles, springs, solver)
    assert added < estimate
    assert estimate - memory.FIXED < 4 * added


def test_a_gradients_kept_states_and_frames_are_counted_before_any_step(monkeypatch):
    """Issue 60: ``steps=6000, checkpoint=1`` on a 128 x 128 cloth kept a numpy state a
    step (4.7 GB) that no check counted, and failed part-way with numpy's memory error;
    refused naming the checkpoint before the simulation is made. The count: 5,999 kept
    states and 6,001 frames of 16,384 particles at 48 bytes (and the integrator's own)."""
    monkeypatch.setattr(memory, "_mem_available", lambda: 3 * GB)
    monkeypatch.setattr(memory, "_cgroup_room", lambda: None)
    monkeypatch.setattr(memory, "_address_space_room", lambda: None)
    from massspring import gradients

    model = ms.load_scene("cloth").with_params(resolution=128).model()
    assert gradients.host_bytes(model, "symplectic", 6000, 6001, 1) == (5999 + 6001) * 48 * 16384
    monkeypatch.setattr(gradients, "Simulation", lambda *a, **k: pytest.fail("a simulation was made"))
    with pytest.raises(memory.MemoryNeedError, match=r"checkpoint: .* needs about 9.44 GB; 3 GB"):
        ms.gradient(model, lambda frames: (0.0, {}), "stiffness", steps=6000, every=1, checkpoint=1)
