"""The multigrid cycle in f32 inside the f64 CG against the f64 cycle, side by side.

For the cloth (``--resolutions``, ks ``--stiffness``, dt 1/60, f64, CG tolerance
``--tol``), each ``--integrators`` entry steps with ``preconditioner="multigrid"`` (the
f64 cycle) and ``"multigrid-f32"`` (``massspring/solvers/multigrid_f32.py``), a fresh
simulation per repeat, the two alternating (the first step of each simulation is
untimed: it compiles), so drifting load on a shared machine hits both alike. Reported
per preconditioner: the median ms per step, its setup share (narrowing and multigrid
setup, ms), CG iterations per step (mean, max; Newton-solved steps: all of a step's
solves) and steps whose CG did not converge; the f32 cycle's step time over the f64
one's; and each run's error at its last step: the largest distance (m) from a run with
the f64 cycle at CG tolerance ``--reference-tol`` (both cycles' runs hold only what
their CG tolerance allows, so the two errors should be alike).

    python benchmarks/multigrid_precision.py
    python benchmarks/multigrid_precision.py --resolutions 128 256 512 --stiffness 1e4 1e6 --steps 4 --repeats 3
"""

import argparse
import statistics
import sys
import time

import numpy as np

import massspring as ms
from massspring.device import ensure_taichi
from massspring.io.files import write_json
import output

VARIANTS = ("multigrid", "multigrid-f32")


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--resolutions", type=int, nargs="+", default=[128, 256, 512])
    p.add_argument("--stiffness", type=float, nargs="+", default=[1e4, 1e6])
    p.add_argument("--integrators", nargs="+", default=["implicit"], choices=["implicit", "backward-euler", "bdf2"])
    p.add_argument("--tol", type=float, default=1e-6, help="relative CG tolerance")
    p.add_argument("--reference-tol", type=float, default=1e-10, help="CG tolerance of the reference run")
    p.add_argument("--steps", type=int, default=4, help="timed steps per simulation")
    p.add_argument("--repeats", type=int, default=2, help="simulations per preconditioner (alternating)")
    output.add_json(p, "multigrid_precision")
    return p.parse_args(argv)


def run(resolution, stiffness, integrator, preconditioner, steps, tol):
    """One simulation: step times (s), setup times (s), CG iterations and failures per
    timed step, and the final positions."""
    scene = ms.load_scene("cloth").with_params(resolution=resolution, stiffness=stiffness)
    sim = scene.simulation(integrator=integrator, dt=1 / 60, preconditioner=preconditioner, cg_tol=tol,
                           cg_max_iter=1000)
    sim.step(1)
    times, setups, iterations, failed = [], [], [], 0
    for _ in range(steps):
        start = time.perf_counter()
        sim.step(1)
        times.append(time.perf_counter() - start)
        stats = sim.solver_stats
        setups.append(stats.setup_s)
        iterations.append(stats.iterations)
        failed += 0 if stats.converged else 1
    positions = sim.positions
    sim.close()
    return times, setups, iterations, failed, positions


def main(argv=None):
    args = parse_args(argv)
    ensure_taichi()
    rows = []
    for integrator in args.integrators:
        for resolution in args.resolutions:
            for stiffness in args.stiffness:
                data = {v: {"times": [], "setups": [], "iterations": [], "failed": 0, "positions": None}
                        for v in VARIANTS}
                reference = run(resolution, stiffness, integrator, "multigrid", args.steps, args.reference_tol)[-1]
                for repeat in range(args.repeats):
                    for variant in (VARIANTS if repeat % 2 == 0 else VARIANTS[::-1]):
                        t, s, its, failed, x = run(resolution, stiffness, integrator, variant, args.steps, args.tol)
                        d = data[variant]
                        d["times"] += t
                        d["setups"] += s
                        d["iterations"] += its
                        d["failed"] += failed
                        d["error_m"] = max(d.get("error_m", 0.0), float(np.abs(x - reference).max()))
                base = statistics.median(data[VARIANTS[0]]["times"])
                print(f"\ncloth {resolution}^2, ks {stiffness:g}, {integrator}, {args.steps + 1} steps")
                print(f"{'preconditioner':>15s} {'ms/step':>9s} {'setup ms':>9s} {'ratio':>6s} {'CG mean':>8s} "
                      f"{'CG max':>6s} {'failed':>6s} {'error m':>9s}")
                for variant in VARIANTS:
                    d = data[variant]
                    step_ms = 1e3 * statistics.median(d["times"])
                    row = {"integrator": integrator, "resolution": resolution, "stiffness": stiffness,
                           "preconditioner": variant, "ms_per_step": step_ms,
                           "setup_ms": 1e3 * statistics.median(d["setups"]),
                           "ratio": step_ms / (1e3 * base), "iterations_mean": statistics.mean(d["iterations"]),
                           "iterations_max": max(d["iterations"]), "cg_failures": d["failed"],
                           "steps_timed": len(d["times"]), "error_m": d["error_m"]}
                    rows.append(row)
                    print(f"{variant:>15s} {step_ms:9.1f} {row['setup_ms']:9.1f} {row['ratio']:6.2f} "
                          f"{row['iterations_mean']:8.1f} {row['iterations_max']:6d} {d['failed']:6d} "
                          f"{d['error_m']:9.2e}", flush=True)
    write_json(args.json, {"dt": 1 / 60, "precision": "f64", "tol": args.tol, "reference_tol": args.reference_tol,
                           "rows": rows})
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
