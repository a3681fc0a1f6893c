"""The device layer: capacity classes, the pool of field bundles, what a closed
Simulation may do, read-only settings, and results independent of the thread count."""

import gc
import subprocess
import sys
import weakref

import numpy as np
import pytest

from conftest import FULL
import massspring as ms
from massspring.device import POOL, capacity, reset_taichi


@pytest.fixture(scope="module")
def cloth():
    model = ms.load_scene("cloth").with_params(resolution=6).model()
    rng = np.random.default_rng(3)
    return ms.Model(model.positions, model.springs, masses=model.masses, stiffness=model.stiffness,
                    damping=model.damping, velocities=rng.normal(scale=0.1, size=model.positions.shape),
                    gravity=model.gravity, fixed=model.fixed)


def test_capacity_classes():
    assert capacity(1, 16) == 16 and capacity(16, 16) == 16 and capacity(17, 16) == 24
    assert capacity(25, 16) == 32 and capacity(33, 16) == 48 and capacity(49, 16) == 64
    for count in range(1, 5000, 7):
        cap = capacity(count, 4)
        assert cap >= count and cap <= 1.5 * max(count, 4) + 1
        assert cap & (cap - 1) == 0 or (cap // 3) & (cap // 3 - 1) == 0  # 2^k or 3 * 2^j


def test_closed_simulation_bundle_is_reused_by_the_next(cloth):
    first = ms.Simulation(cloth, integrator="implicit", dt=1 / 60)
    first.step(2)
    expected = first.positions
    first.close()
    idle, created = POOL.idle(), POOL.created
    second = ms.Simulation(cloth, integrator="implicit", dt=1 / 60)
    assert POOL.idle() == idle - 1 and POOL.created == created  # taken from the pool, no new fields
    assert np.array_equal(second.positions, cloth.positions)  # refilled from the model
    second.step(2)
    np.testing.assert_array_equal(second.positions, expected)  # the same run, to the bit
    second.close()


def test_use_after_close_raises_and_cannot_touch_the_next_run(cloth):
    a = ms.Simulation(cloth, integrator="symplectic", dt=1e-4)
    a.step(2)
    a.close()
    a.close()  # idempotent
    assert a.closed
    b = ms.Simulation(cloth, integrator="symplectic", dt=1e-4)  # takes a's fields from the pool
    before = b.positions
    for call in (lambda: a.step(1), lambda: a.positions, lambda: a.velocities, lambda: a.info(),
                 lambda: a.energy(), lambda: a.solver_stats):
        with pytest.raises(ms.SimulationClosedError, match="closed"):
            call()
    np.testing.assert_array_equal(b.positions, before)
    assert a.steps == 2 and a.dt == 1e-4  # plain settings and counters stay readable


def test_settings_are_read_only(cloth):
    sim = ms.Simulation(cloth, integrator="explicit", dt=1e-4)
    for name, value in (("dt", 1.0), ("integrator", "implicit"), ("check", (0, 0, 0)), ("steps", 5),
                        ("precision", "f32"), ("model", None)):
        with pytest.raises(AttributeError):
            setattr(sim, name, value)
    assert sim.dt == 1e-4 and sim.settings.dt == 1e-4


def test_bad_loops_named():
    model = ms.Model([[0, 0, 0], [1, 0, 0]], [[0, 1]])
    with pytest.raises(ValueError, match="^loops"):
        ms.Simulation(model, loops="threads")


def test_simulations_are_garbage_collected_and_their_fields_pooled():
    model = ms.Model([[0, 0, 0], [1, 0, 0]], [[0, 1]], gravity=(0, 0, -1.0))
    refs = []
    for integrator in ("explicit", "implicit"):
        sim = ms.Simulation(model, integrator=integrator)
        sim.step(1)
        refs.append(weakref.ref(sim))
        idle = POOL.idle()
        del sim
        assert POOL.idle() == idle + 1  # released at once, without close()
    gc.collect()
    assert all(ref() is None for ref in refs)


# (scene, resolution, integrator, preconditioner, steps); the fast tier runs the first and the sixth
THREAD_CASES = [("cloth", 32, "implicit", "block-jacobi", 10), ("cloth", 128, "implicit", "multigrid", 2),
                ("drape", 32, "implicit", "multigrid", 20), ("drape", 32, "backward-euler", "multigrid", 2),
                ("flag", None, "bdf2", "block-jacobi", 3), ("cloth", 32, "symplectic", None, 50),
                ("drape", 32, "explicit", None, 50), ("flag", None, "rk4", None, 50)]
THREADS_SCRIPT = """
import hashlib, sys
import massspring as ms
for name, resolution, integrator, preconditioner, steps in eval(sys.argv[1]):
    scene = ms.load_scene(name)
    if resolution:
        scene = scene.with_params(resolution=resolution)
    options = {} if preconditioner is None else {"preconditioner": preconditioner}
    sim = scene.simulation(integrator, loops="parallel", **options)
    sim.step(steps)
    print(hashlib.sha256(sim.positions.tobytes() + sim.velocities.tobytes()).hexdigest(), sum(sim.cg_iterations))
    sim.close()
"""


@FULL
def test_a_simulation_collected_after_a_reset_does_not_return_dead_fields():
    """``reset_taichi`` frees every field; a Simulation of the old runtime collected after
    it must not put its bundle back in the pool, where the next run of that size would
    take it (a use of freed memory: it crashed the process)."""
    def chain():
        return ms.Model([[0, 0, 0], [1, 0, 0], [2, 0, 0]], [[0, 1], [1, 2]], fixed=[0])

    old = ms.Simulation(chain(), "implicit", dt=1e-2)
    old.step(2)
    reset_taichi()
    del old
    gc.collect()
    assert POOL.idle() == 0
    runs = [ms.Simulation(chain(), "implicit", dt=1e-2) for _ in range(2)]
    for sim in runs:
        sim.step(5)
    assert np.array_equal(runs[0].positions, runs[1].positions)
    assert np.all(np.isfinite(runs[0].positions)) and runs[0].positions[2, 2] < 0


@FULL
def test_parallel_results_do_not_depend_on_the_thread_count():
    """Reductions sum fixed blocks in order (kernels/blocks.py), multigrid kernels write
    each entry from one thread and its cycle's r . z is a fixed-block sum too: 1 and 2
    threads give the same bits for every integrator and preconditioner, on cloth at
    32 x 32 and 128 x 128 (where ``auto`` picks multigrid), drape at 32 x 32 (contact) and flag
    (wind). Before, 100 cloth steps differed by up to 4.8e-6 m, and one multigrid step
    of the 128 x 128 cloth differed. Each child compiles its own kernels (Taichi's
    offline cache keys them by the thread count too, so a shared one never hits)."""
    import os

    cases = THREAD_CASES
    out = []
    for threads in ("1", "2"):
        env = dict(os.environ, TI_CPU_MAX_NUM_THREADS=threads, TI_OFFLINE_CACHE="0")
        proc = subprocess.run([sys.executable, "-c", THREADS_SCRIPT, repr(cases)], capture_output=True, text=True,
                              env=env, timeout=600)
        assert proc.returncode == 0, proc.stderr
        out.append(proc.stdout.split()[-2 * len(cases):])  # after Taichi's banner
    assert len(out[0]) == 2 * len(cases) and out[0] == out[1]


def test_serial_and_parallel_loops_agree_to_the_bit_on_explicit_steps(cloth):
    runs = []
    for loops in ("serial", "parallel"):
        sim = ms.Simulation(cloth, integrator="symplectic", dt=1e-4, loops=loops)
        sim.step(25)
        runs.append((sim.positions, sim.velocities))
        sim.close()
    np.testing.assert_array_equal(runs[0][0], runs[1][0])
    np.testing.assert_array_equal(runs[0][1], runs[1][1])


@FULL
def test_memory_does_not_grow_with_the_number_of_simulations():
    """Before, every Simulation kept about 48 KB (196 to 266 MiB over 1,500 runs);
    now its fields go back to the pool and nothing else stays: 300 more runs, half of
    them closed and half dropped, grow the peak RSS by well under the 14 MB they cost."""
    import resource

    model = ms.load_scene("cloth").with_params(resolution=6).model()

    def runs(count):
        for k in range(count):
            sim = ms.Simulation(model, integrator="implicit", dt=1 / 60)
            sim.step(1)
            if k % 2:
                sim.close()
            del sim

    runs(50)  # compiled, pooled
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux
    runs(300)
    growth_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before
    assert growth_kib < 4 * 1024, growth_kib


def test_taichi_leaves_python_reading_subnormal_numbers():
    """Issue 60: ``ti.init`` turns on flush-to-zero and denormals-are-zero, after which
    Python read ``float("1e-320")`` as 0.0: ``--set strain_limit=1e-320`` silently became
    no limit, and ``Model(strain_limit=1e-320)`` was accepted before the first simulation
    and refused after it. In a fresh process (Taichi not yet started), the numbers read
    after a simulation are those read before it."""
    script = (
        "import tomllib, massspring as ms\n"
        "before = (float('1e-320'), tomllib.loads('v = 1e-320')['v'], 5e-324 * 1.5)\n"
        "sim = ms.load_scene('spring').simulation(); sim.step(2); sim.close()\n"
        "after = (float('1e-320'), tomllib.loads('v = 1e-320')['v'], 5e-324 * 1.5)\n"
        "print(before == after, before[0] > 0)\n")
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["True", "True"], out.stdout + out.stderr
