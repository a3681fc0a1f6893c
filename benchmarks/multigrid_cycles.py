"""Multigrid cycle shapes side by side: W- or V-cycle, Chebyshev degree, in one run.

Each variant sets ``massspring.solvers.multigrid``'s ``W_CYCLE``, the smoother
degree (``chebyshev``'s default, ``NU``) and ``aggregation.FILTER_WEAK`` (False:
"all couplings", level 0's weak couplings kept in P and the coarse operators) for
the whole process, then steps the cloth
(``--resolutions``, ``--stiffness``, dt 1/60, f64, CG tolerance 1e-6) with the
multigrid-preconditioned implicit step. Variants are interleaved per repeat (the
first step of each simulation is untimed: it compiles), so drifting load on a
shared machine hits all alike. Reported per variant: median ms per step, CG
iterations per step (mean, max) and the ratio of the step time to the default's
(W, degree 3) measured in the same run.

    python benchmarks/multigrid_cycles.py
    python benchmarks/multigrid_cycles.py --resolutions 128 256 --stiffness 1e4 1e6 --steps 4 --repeats 3
"""

import argparse
import statistics
import sys
import time

import massspring as ms
from massspring.device import ensure_taichi
from massspring.io.files import write_json
from massspring.solvers import aggregation, multigrid
import output

# name: (W-cycle, Chebyshev degree, level 0's weak couplings left out of the coarse levels)
VARIANTS = {"W, degree 3": (True, 3, True), "V, degree 3": (False, 3, True), "W, degree 2": (True, 2, True),
            "V, degree 2": (False, 2, True), "V, degree 4": (False, 4, True), "V, degree 5": (False, 5, True),
            "V, degree 3, all couplings": (False, 3, False)}


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--resolutions", type=int, nargs="+", default=[128, 256])
    p.add_argument("--stiffness", type=float, nargs="+", default=[1e4, 1e6])
    p.add_argument("--steps", type=int, default=4, help="timed steps per simulation")
    p.add_argument("--repeats", type=int, default=2, help="simulations per variant (interleaved)")
    p.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    output.add_json(p, "multigrid_cycles")
    return p.parse_args(argv)


def run(resolution, stiffness, variant, steps):
    w_cycle, degree, filter_weak = VARIANTS[variant]
    saved = multigrid.W_CYCLE, multigrid.chebyshev.__defaults__, aggregation.FILTER_WEAK
    multigrid.W_CYCLE = w_cycle
    multigrid.chebyshev.__defaults__ = (degree, saved[1][1])
    aggregation.FILTER_WEAK = filter_weak
    try:
        scene = ms.load_scene("cloth").with_params(resolution=resolution, stiffness=stiffness)
        sim = scene.simulation(integrator="implicit", dt=1 / 60, preconditioner="multigrid")
        sim.step(1)
        times = []
        for _ in range(steps):
            start = time.perf_counter()
            sim.step(1)
            times.append(time.perf_counter() - start)
        iterations = sim.cg_iterations[1:]
        failures = sim.cg_failures
        sim.close()
    finally:
        multigrid.W_CYCLE, multigrid.chebyshev.__defaults__, aggregation.FILTER_WEAK = saved
    return times, iterations, failures


def main(argv=None):
    args = parse_args(argv)
    ensure_taichi()
    rows = []
    for resolution in args.resolutions:
        for stiffness in args.stiffness:
            times = {v: [] for v in args.variants}
            iterations = {v: [] for v in args.variants}
            failures = dict.fromkeys(args.variants, 0)
            for repeat in range(args.repeats):
                order = args.variants if repeat % 2 == 0 else args.variants[::-1]
                for variant in order:
                    t, its, failed = run(resolution, stiffness, variant, args.steps)
                    times[variant] += t
                    iterations[variant] += its
                    failures[variant] += failed
            base = statistics.median(times[args.variants[0]])
            print(f"\ncloth {resolution}^2, ks {stiffness:g}")
            print(f"{'variant':>12s} {'ms/step':>9s} {'ratio':>6s} {'iter mean':>9s} {'iter max':>8s} {'failed':>6s}")
            for variant in args.variants:
                ms_step = 1e3 * statistics.median(times[variant])
                row = {"resolution": resolution, "stiffness": stiffness, "variant": variant, "ms_per_step": ms_step,
                       "ratio": ms_step / (1e3 * base), "iterations_mean": statistics.mean(iterations[variant]),
                       "iterations_max": max(iterations[variant]), "cg_failures": failures[variant]}
                rows.append(row)
                print(f"{variant:>12s} {ms_step:9.1f} {row['ratio']:6.2f} {row['iterations_mean']:9.1f} "
                      f"{row['iterations_max']:8d} {failures[variant]:6d}", flush=True)
    write_json(args.json, {"dt": 1 / 60, "precision": "f64", "rows": rows})
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
