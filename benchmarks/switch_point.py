"""Where serial and parallel kernels pay off.

For cloths of increasing resolution, times the implicit step (ms per CG
iteration with block-Jacobi; ms per step with multigrid, setup included) and the
symplectic step (ms per step) with serial kernels (a whole solve, or many explicit
steps, per launch) and parallel kernels (one launch per phase), all in one run. The
default ``simulation.SERIAL_BELOW`` comes from this table.

    python benchmarks/switch_point.py --help
    python benchmarks/switch_point.py --resolutions 128 256 384 512   # results/switch_point_intel.json
"""

import argparse
import statistics
import sys
import time

import massspring as ms
from massspring.analysis.stability import predict
from massspring.integrators import INTEGRATORS
from massspring.io.files import write_json
import output

COMBOS = ["serial", "parallel"]


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--resolutions", type=int, nargs="+", default=[32, 128, 256, 384, 512])
    p.add_argument("--steps", type=int, default=3, help="timed implicit steps (after one warm-up step)")
    p.add_argument("--explicit-steps", type=int, default=200, help="timed symplectic steps per run")
    output.add_json(p, "switch_point")
    return p.parse_args(argv)


def implicit_ms_per_iteration(scene, loops, steps):
    sim = scene.simulation(integrator="implicit", dt=1 / 60, loops=loops, preconditioner="block-jacobi")
    t0 = time.perf_counter()
    sim.step(1)
    first = time.perf_counter() - t0
    per_iter = []
    for _ in range(steps):
        t0 = time.perf_counter()
        sim.step(1)
        per_iter.append((time.perf_counter() - t0) / max(sim.solver_stats.iterations, 1))
    sim.close()
    return 1e3 * statistics.median(per_iter), first


def multigrid_ms_per_step(scene, loops, steps):
    sim = scene.simulation(integrator="implicit", dt=1 / 60, loops=loops, preconditioner="multigrid")
    sim.step(1)
    times = []
    for _ in range(steps):
        t0 = time.perf_counter()
        sim.step(1)
        times.append(time.perf_counter() - t0)
    sim.close()
    return 1e3 * statistics.median(times)


def symplectic_ms_per_step(scene, loops, steps, dt):
    sim = scene.simulation(integrator="symplectic", dt=dt, loops=loops)
    sim.step(1)
    times = []
    for _ in range(3):
        t0 = time.perf_counter()
        sim.step(steps)
        times.append((time.perf_counter() - t0) / steps)
    sim.close()
    return 1e3 * statistics.median(times)


def main(argv=None):
    args = parse_args(argv)
    header = "  ".join(f"{loops:>10s}" for loops in COMBOS)
    print(f"{'res':>4s} {'springs':>8s}  implicit ms/iteration: {header}   multigrid ms/step: {header}   "
          f"symplectic ms/step: {header}")
    rows = []
    for resolution in args.resolutions:
        scene = ms.load_scene("cloth").with_params(resolution=resolution)
        # the scene's [dt] is for its own size: the symplectic dt comes from the stability estimate
        dt = INTEGRATORS["symplectic"].suggest_dt(predict(scene.model()))
        row = {"resolution": resolution, "springs": scene.model().n_springs, "implicit": {}, "multigrid": {},
               "symplectic": {}, "compile_s": {}}
        for loops in COMBOS:
            row["implicit"][loops], row["compile_s"][loops] = implicit_ms_per_iteration(scene, loops, args.steps)
            row["multigrid"][loops] = multigrid_ms_per_step(scene, loops, args.steps)
            row["symplectic"][loops] = symplectic_ms_per_step(scene, loops, args.explicit_steps, dt)
        rows.append(row)
        imp = "  ".join(f"{row['implicit'][loops]:10.4f}" for loops in COMBOS)
        mg = "  ".join(f"{row['multigrid'][loops]:10.1f}" for loops in COMBOS)
        sym = "  ".join(f"{row['symplectic'][loops]:10.4f}" for loops in COMBOS)
        print(f"{resolution:4d} {row['springs']:8d}  {'':22s}{imp}   {'':18s}{mg}   {'':19s}{sym}", flush=True)
    write_json(args.json, rows)
    print(f"wrote {args.json}")


if __name__ == "__main__":
    sys.exit(main())
