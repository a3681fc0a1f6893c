"""Where a multigrid-preconditioned implicit step spends its time, level by level.

For the cloth (``--resolutions``, ks ``--stiffness``, dt 1/60, f64) this runs a few
implicit steps with ``preconditioner="multigrid"`` and times every kernel launch of
the preconditioner (``massspring.solvers.multigrid`` drives the cycle and the setup
level by level from Python; a CPU launch returns when its kernel is done, so wall
time around each launch is its cost). Each launch is charged to the level whose
unknowns it works on: level 0 is the particles (matrix-free), level l >= 1 the
aggregates of level l - 1 (6 unknowns each, 6x6 blocks); the restriction to level
l counts at level l, the coarsest solve at the last level.

Then the step's cost in that unit, the issue's measure: ``--repeats`` pairs of one
multigrid step (untimed kernels) and one unit sample, interleaved so that the
machine's drift hits both alike; the median of the pairs' ratios and their range.

Printed per level, for the cycle (per CG iteration) and for the setup (per step):
unknowns, stored operator blocks and their bytes (level 0: the per-entry spring
coefficients it reads instead), visits per cycle (a V-cycle visits each level once;
a W-cycle (``W_CYCLE``) visits each level twice per visit of its parent, but the last
level once), ms, that time in units of one fine-level matrix-free product, measured
in the same run as one block-Jacobi CG iteration of the same cloth (its product plus
vector updates: the unit issue 22 counts in), and kernel launches (each costs about
0.1 ms with parallel loops on this project's machines, ``launch_cost.py``).

    python benchmarks/multigrid_levels.py
    python benchmarks/multigrid_levels.py --resolutions 128 256 --steps 4
"""

import argparse
import collections
import statistics
import sys
import time

import massspring as ms
from massspring.device import ensure_taichi
from massspring.io.files import write_json
from massspring.solvers import multigrid
import output
from roofline import IterationTimer


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--resolutions", type=int, nargs="+", default=[128, 256])
    p.add_argument("--stiffness", type=float, default=1e4)
    p.add_argument("--steps", type=int, default=3, help="timed steps per resolution (after one untimed)")
    p.add_argument("--repeats", type=int, default=7,
                   help="interleaved pairs of a multigrid step and a block-Jacobi unit sample")
    p.add_argument("--preconditioner", default="multigrid", choices=["multigrid", "multigrid-f32"],
                   help="multigrid-f32: the finest level in f32 (its narrowing after the setup is in the step "
                   "time, not in a level's)")
    output.add_json(p, "multigrid_levels")
    return p.parse_args(argv)


class Timer:
    """Stands in for ``kernels/multigrid.py`` inside ``solvers/multigrid.py``: every
    kernel call is timed and charged to (phase, level, kernel)."""

    def __init__(self, module, plan):
        self.module, self.plan = module, plan
        self.phase = "cycle"
        self.level_stack = [0]
        self.seconds = collections.defaultdict(float)
        self.calls = collections.Counter()
        last = plan.levels - 1
        self.ranges = {}
        for table in ("node_range", "gal_range", "lower_range"):
            for level, pair in getattr(plan, table, {}).items():
                self.ranges.setdefault((table, tuple(pair)), level)
        self.last = last

    def level_of(self, name, args):
        if name in ("factor_coarsest", "solve_coarsest"):
            return self.last
        if name.endswith("0") or name == "fine_inverse":
            return 0
        table = {"galerkinc": "gal_range", "mirror": "lower_range"}.get(name, "node_range")
        ints = [a for a in args if isinstance(a, int) and not isinstance(a, bool)]
        for a, b in zip(ints, ints[1:]):
            if (table, (a, b)) in self.ranges:
                return self.ranges[(table, (a, b))]
        return self.level_stack[-1]

    def __getattr__(self, name):
        kernel = getattr(self.module, name)
        if not callable(kernel):
            return kernel

        def timed(*args, **kwargs):
            start = time.perf_counter()
            result = kernel(*args, **kwargs)
            key = (self.phase, self.level_of(name, args), name)
            self.seconds[key] += time.perf_counter() - start
            self.calls[key] += 1
            return result
        return timed


def level_table(pre, springs):
    """Per level: unknowns, stored blocks and bytes of its operator (level 0: the
    coefficients of its ``springs`` that the cycle reads, two entries each)."""
    levels = pre.hierarchy.levels
    rows = []
    for l, level in enumerate(levels):
        off = 2 * springs if l == 0 else len(level.off_cols)
        blocks = level.n + off
        block_bytes = 8 * level.bs * level.bs
        rows.append({"level": l, "nodes": level.n, "unknowns": level.n * level.bs, "blocks": blocks,
                     "operator_mb": (blocks * block_bytes if l else off * (4 + 5 * 8)) / 1e6})
    return rows


def measure(resolution, stiffness, steps, repeats, preconditioner="multigrid"):
    scene = ms.load_scene("cloth").with_params(resolution=resolution, stiffness=stiffness)
    sim = scene.simulation(integrator="implicit", dt=1 / 60, preconditioner=preconditioner)
    pre = sim.stepper.preconditioner
    sim.step(1)  # compile everything
    timer = Timer(multigrid.mg, pre.plan)
    original_setup, original_coarse = pre.setup, pre._coarse

    def setup(dt):
        timer.phase = "setup"
        try:
            return original_setup(dt)
        finally:
            timer.phase = "cycle"

    def coarse(level, first):
        timer.level_stack.append(level)
        try:
            return original_coarse(level, first)
        finally:
            timer.level_stack.pop()

    pre.setup, pre._coarse = setup, coarse
    multigrid.mg = timer
    iterations, setups = [], []
    try:
        for _ in range(steps):
            sim.step(1)
            iterations.append(sim.solver_stats.iterations)
            setups.append(sim.solver_stats.setup_s)
    finally:
        multigrid.mg = timer.module
        pre.setup, pre._coarse = original_setup, original_coarse
    pairs = interleaved(sim, IterationTimer(scene, sim.loops, 40, "f64"), repeats)
    loops = sim.loops
    sim.close()
    unit = statistics.median(pairs["unit_s"])
    cycles = sum(c for (phase, _, name), c in timer.calls.items() if name == "up0")  # one per cycle
    rows = level_table(pre, scene.model().n_springs)
    for row in rows:
        l = row["level"]
        for phase, per in (("cycle", cycles), ("setup", steps)):
            seconds = sum(t for (p, level, _), t in timer.seconds.items() if p == phase and level == l)
            row[f"{phase}_ms"] = 1e3 * seconds / per
            row[f"{phase}_launches"] = sum(c for (p, level, _), c in timer.calls.items()
                                           if p == phase and level == l) / per
            row[f"{phase}_in_products"] = seconds / per / unit
        visits = sum(c for (p, level, name), c in timer.calls.items()
                     if p == "cycle" and level == l and name in ("down0", "downc", "solve_coarsest"))
        row["visits_per_cycle"] = visits / cycles
    kernels = {f"{p}/{level}/{name}": 1e3 * t / (cycles if p == "cycle" else steps)
               for (p, level, name), t in sorted(timer.seconds.items())}
    return {"resolution": resolution, "particles": sim.model.n_particles, "springs": sim.model.n_springs,
            "loops": loops, "step_ms": 1e3 * statistics.median(pairs["step_s"]), "iterations": iterations,
            "step_in_units": statistics.median(pairs["ratio"]), "step_in_units_range": [min(pairs["ratio"]), max(pairs["ratio"])],
            "interleaved": pairs,
            "setup_ms": 1e3 * statistics.median(setups), "unit_ms": 1e3 * unit,
            "cycle_ms": sum(r["cycle_ms"] for r in rows), "setup_kernels_ms": sum(r["setup_ms"] for r in rows),
            "levels": rows, "kernels_ms": kernels}


def interleaved(sim, unit, repeats):
    """``repeats`` pairs: one step of ``sim`` (s, CG iterations), then one sample of the
    ``IterationTimer`` ``unit``; each pair's ratio step / unit."""
    pairs = {"step_s": [], "iterations": [], "unit_s": [], "ratio": []}
    try:
        for _ in range(repeats):
            start = time.perf_counter()
            sim.step(1)
            pairs["step_s"].append(time.perf_counter() - start)
            pairs["iterations"].append(sim.solver_stats.iterations)
            pairs["unit_s"].append(unit.sample())
            pairs["ratio"].append(pairs["step_s"][-1] / pairs["unit_s"][-1])
    finally:
        unit.close()
    return pairs


def main(argv=None):
    args = parse_args(argv)
    ensure_taichi()
    results = []
    for resolution in args.resolutions:
        r = measure(resolution, args.stiffness, args.steps, args.repeats, args.preconditioner)
        results.append(r)
        print(f"\ncloth {resolution}^2 ({r['particles']:,} particles, {r['springs']:,} springs, ks "
              f"{args.stiffness:g}, {r['loops']} loops): CG iterations {r['iterations']}, setup "
              f"{r['setup_ms']:.1f} ms (median)")
        print(f"{'level':>5s} {'unknowns':>9s} {'blocks':>9s} {'MB':>7s} {'visits':>6s} {'cycle ms':>9s} "
              f"{'products':>8s} {'launches':>8s} {'setup ms':>9s} {'products':>8s} {'launches':>8s}")
        for row in r["levels"]:
            print(f"{row['level']:5d} {row['unknowns']:9,d} {row['blocks']:9,d} {row['operator_mb']:7.2f} "
                  f"{row['visits_per_cycle']:6.0f} {row['cycle_ms']:9.3f} {row['cycle_in_products']:8.1f} "
                  f"{row['cycle_launches']:8.1f} {row['setup_ms']:9.3f} {row['setup_in_products']:8.1f} "
                  f"{row['setup_launches']:8.1f}")
        print(f"{'all':>5s} {'':>9s} {'':>9s} {'':>7s} {'':>6s} {r['cycle_ms']:9.3f} "
              f"{r['cycle_ms'] / r['unit_ms']:8.1f} {sum(x['cycle_launches'] for x in r['levels']):8.1f} "
              f"{r['setup_kernels_ms']:9.3f} {r['setup_kernels_ms'] / r['unit_ms']:8.1f} "
              f"{sum(x['setup_launches'] for x in r['levels']):8.1f}")
        low, high = r["step_in_units_range"]
        print(f"interleaved ({args.repeats} pairs, medians): step {r['step_ms']:.1f} ms (CG iterations "
              f"{r['interleaved']['iterations']}), one block-Jacobi CG iteration (the unit) {r['unit_ms']:.3f} ms; "
              f"the step costs {r['step_in_units']:.0f} block-Jacobi CG iterations (pairs: {low:.0f}-{high:.0f}; "
              f"issue 22's target: at most 100)")
    write_json(args.json, {"stiffness": args.stiffness, "dt": 1 / 60, "precision": "f64",
                           "preconditioner": args.preconditioner, "results": results})
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
