"""One measurement of ``compare_revisions.py``, printed as JSON: {"case", "value"}.

Only public API that every revision since the first release has (``load_scene``,
``Scene.with_params``, ``Scene.simulation``, ``Simulation.step``,
``solver_stats``, ``preconditioner="block-jacobi"``), so the same file measures old and
new code: block-Jacobi CG iterations (the default below ``solvers.MULTIGRID_FROM`` free particles now).
The multigrid cases need ``preconditioner="multigrid"``: revisions since it was added.

    python benchmarks/measure_case.py implicit-128
"""

import json
import statistics
import sys
import time

import massspring as ms

ITERATIONS = 20  # CG iterations of the shorter capped solve (the longer has twice as many) ...
LARGE_ITERATIONS = 100  # ... above 128^2, where 20 parallel iterations are too short to time on a shared machine


def cloth(resolution):
    return ms.load_scene("cloth").with_params(resolution=resolution)


def implicit_ms_per_iteration(resolution, repeats=3):
    """(t(2k) - t(k)) / k over solves capped at k and 2k iterations: the iteration alone."""
    scene = cloth(resolution)

    def solve_seconds(limit):
        sim = scene.simulation(integrator="implicit", dt=1 / 60, cg_max_iter=limit, preconditioner="block-jacobi")
        sim.step(1)  # compile, and leave the flat start behind
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            sim.step(1)
            times.append(time.perf_counter() - t0)
            assert sim.solver_stats.iterations == limit, sim.solver_stats
        return statistics.median(times)

    k = ITERATIONS if resolution <= 128 else LARGE_ITERATIONS
    return 1e3 * (solve_seconds(2 * k) - solve_seconds(k)) / k


def ms_per_step(sim, steps, runs):
    """Median over ``runs`` timed calls of ``sim.step(steps)`` of the ms per step, after two
    untimed steps (compilation, and an implicit flat start's one-iteration solve)."""
    sim.step(2)
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        sim.step(steps)
        times.append((time.perf_counter() - t0) / steps)
    return 1e3 * statistics.median(times)


def explicit_ms_per_step(integrator, resolution, repeats=3):
    sim = cloth(resolution).simulation(integrator=integrator, dt=2e-4 / resolution)
    return ms_per_step(sim, max(10, int(4e6 / sim.model.n_springs)), repeats)


def multigrid_ms_per_step(resolution, steps=4):
    """A whole implicit step with the multigrid preconditioner (setup and solve), dt 1/60:
    the median of ``steps`` single steps."""
    sim = cloth(resolution).simulation(integrator="implicit", dt=1 / 60, preconditioner="multigrid")
    return ms_per_step(sim, 1, steps)


def sheets_ms_per_step(integrator, resolution):
    """The ``sheets`` scene (two sheets, the upper one landing on the lower, self-collision
    every step) at its dt: ms per step over 3 x 40 steps from step 2 on (they land about
    step 45 at 1/240 s)."""
    sim = ms.load_scene("sheets").with_params(resolution=resolution).simulation(integrator=integrator)
    return ms_per_step(sim, 40, 3)


def cold_first_step(integrator, resolution):
    """Seconds from building the Simulation to the end of its first step (kernels
    compiled: run with an empty Taichi offline cache)."""
    scene = cloth(resolution)
    scene.model()  # the scene's own numpy work is not compilation
    t0 = time.perf_counter()
    sim = scene.simulation(integrator=integrator, tol=None)
    sim.step(1)
    sim.positions  # noqa: B018 - the readback kernel too
    return time.perf_counter() - t0


def main(case):
    kind, _, size = case.rpartition("-")
    resolution = int(size)
    if kind == "implicit":
        value = implicit_ms_per_iteration(resolution)
    elif kind in ("explicit", "symplectic"):
        value = explicit_ms_per_step(kind, resolution)
    elif kind == "multigrid":
        value = multigrid_ms_per_step(resolution)
    elif kind.startswith("sheets-"):
        value = sheets_ms_per_step(kind[len("sheets-"):], resolution)
    elif kind.startswith("cold-"):
        value = cold_first_step(kind[len("cold-"):], resolution)
    else:
        raise SystemExit(f"unknown case {case!r}")
    print(json.dumps({"case": case, "value": value}))


if __name__ == "__main__":
    main(sys.argv[1])
