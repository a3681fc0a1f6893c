"""Multigrid setup reused across steps (issue 22): step time and CG iterations against a full setup every step.

``Multigrid.setup`` runs the whole setup every step. Each variant here replaces it on
one simulation (``Reuse``): a full setup every ``k`` setups (and, adaptive, also when
the last solve took more than ``growth`` times the iterations of the first solve after
the last full setup); on the other steps only level 0's D^-1 and rho[0]
(``fine_level``, the fine smoother stays convergent for the current A, so the cycle
stays symmetric positive definite) and, in the "P" variants, the coarse operators
too (``coarse_operators``: the Galerkin products of the stale P with the current A).

Cases are ``scene:resolution:stiffness`` (the scene's generator takes both; dt 1/60,
f64, CG tolerance 1e-6, the multigrid forced). All variants of a case are built
first and stepped in turn, one step each, the order reversed every step, so
drifting load on a shared machine hits all alike; the ``--warm`` first steps are
untimed (compilation; they run the variant's rule too). Reported per variant:
median and mean ms per step (setup included; the mean is what a cycle of full and
reused setups costs), their ratios to the first variant's (k=1, a full setup every
step) in the same run, median setup ms, CG iterations per step (mean, max, each
step's), full setups (warm steps included), the largest true relative residual CG
stopped at (its contract: at most the tolerance) and steps that did not converge
(warm steps included). A stale hierarchy can take thousands of iterations a step
(cloth 128^2 at ks 1e6, k=4): the committed results ran fewer variants and steps
where it does.

    python benchmarks/multigrid_reuse.py  # cloth 64^2, quick

The committed results (``benchmarks/results/multigrid_reuse_*.json``), one command each:

    python benchmarks/multigrid_reuse.py --cases cloth:128:1e4 --steps 12 --json benchmarks/results/multigrid_reuse_128_1e4.json
    python benchmarks/multigrid_reuse.py --cases cloth:128:1e6 --steps 6 --variants k=1 k=2 k=4 "adaptive 1.5" "P k=2" "P k=4" --json benchmarks/results/multigrid_reuse_128_1e6.json
    python benchmarks/multigrid_reuse.py --cases cloth:256:1e4 --steps 6 --variants k=1 k=2 "P k=2" --json benchmarks/results/multigrid_reuse_256_1e4.json
    python benchmarks/multigrid_reuse.py --cases cloth:256:1e6 --steps 4 --variants k=1 k=2 "P k=2" --json benchmarks/results/multigrid_reuse_256_1e6.json
    python benchmarks/multigrid_reuse.py --cases drape:128:1e4 --steps 12 --warm 30 --variants k=1 k=2 k=4 k=8 "adaptive 1.5" "P k=2" --json benchmarks/results/multigrid_reuse_drape.json
    python benchmarks/multigrid_reuse.py --cases drape:128:1e4 --steps 14 --warm 4 --variants k=1 k=2 k=4 k=8 "adaptive 1.5" "P k=2" --json benchmarks/results/multigrid_reuse_drape_falling.json

(the drape's cloth falls freely until about step 21, then lies on the sphere).
"""

import argparse
import statistics
import sys
import time

import massspring as ms
from massspring.device import ensure_taichi
from massspring.io.files import write_json
import output

# name: (k, growth or None, what a step without the full setup refreshes)
VARIANTS = {"k=1": (1, None, "fine"), "k=2": (2, None, "fine"), "k=4": (4, None, "fine"), "k=8": (8, None, "fine"),
            "adaptive 1.5": (32, 1.5, "fine"), "P k=2": (2, None, "coarse"), "P k=4": (4, None, "coarse")}
CASES = ["cloth:64:1e4", "cloth:64:1e6"]  # quick; the committed results name theirs (above)


class Reuse:
    """Replaces ``mg.setup`` (a ``solvers.multigrid.Multigrid``) by a full setup every
    ``every`` setups, or when ``last`` (the last solve's CG iterations, set by the
    caller) passes ``growth`` times ``baseline`` (the first solve's after the last
    full setup); otherwise ``fine_level`` only ("fine") or with ``coarse_operators``
    ("coarse")."""

    def __init__(self, mg, every, growth, partial):
        self.mg, self.every, self.growth, self.partial = mg, every, growth, partial
        self.age = None  # setups since the last full one; None before the first
        self.baseline = self.last = None
        self.full = 0
        mg.setup = self.setup

    def due(self):
        if self.age is None or self.age >= self.every:
            return True
        return (self.growth is not None and self.baseline is not None
                and self.last > self.growth * self.baseline)

    def setup(self, dt):
        mg = self.mg
        mg.fine_level()
        if mg.g is None:
            return
        if self.due():
            self.age, self.baseline = 1, None
            self.full += 1
            mg.prolongation()
            mg.coarse_operators()
            return
        self.age += 1
        if self.partial == "coarse":
            mg.coarse_operators()

    def solved(self, iterations):
        self.last = iterations
        if self.baseline is None:
            self.baseline = max(iterations, 1)


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cases", nargs="+", default=CASES, help="scene:resolution:stiffness")
    p.add_argument("--steps", type=int, default=8, help="timed steps per variant")
    p.add_argument("--warm", type=int, default=1, help="untimed steps first")
    p.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    output.add_json(p, "multigrid_reuse")
    return p.parse_args(argv)


def build(case, variant):
    name, resolution, stiffness = case.split(":")
    scene = ms.load_scene(name).with_params(resolution=int(resolution), stiffness=float(stiffness),
                                            strain_limit=0.0)  # the drape's off, as its results were measured
    sim = scene.simulation(integrator="implicit", dt=1 / 60, precision="f64", cg_tol=1e-6, preconditioner="multigrid")
    return sim, Reuse(sim.stepper.preconditioner, *VARIANTS[variant])


def step(sim, reuse):
    start = time.perf_counter()
    sim.step(1)
    elapsed = time.perf_counter() - start
    reuse.solved(sim.cg_iterations[-1])
    return elapsed


def main(argv=None):
    args = parse_args(argv)
    ensure_taichi()
    rows = []
    for case in args.cases:
        runs = {v: build(case, v) for v in args.variants}
        times, setup, residual = ({v: [] for v in args.variants} for _ in range(3))
        for sim, reuse in runs.values():
            for _ in range(args.warm):
                step(sim, reuse)
        for k in range(args.steps):
            for v in (args.variants if k % 2 == 0 else args.variants[::-1]):
                sim = runs[v][0]
                times[v].append(step(*runs[v]))
                setup[v].append(sim.solver_stats.setup_s)
                residual[v].append(sim.solver_stats.residual)
            print(f"step {k}: " + " ".join(f"{v} {runs[v][0].cg_iterations[-1]}" for v in args.variants),
                  file=sys.stderr, flush=True)
        base = statistics.median(times[args.variants[0]])
        print(f"\n{case}: {args.steps} steps after {args.warm}")
        print(f"{'variant':>13s} {'ms/step':>8s} {'ratio':>6s} {'mean ms':>8s} {'ratio':>6s} {'setup ms':>8s} "
              f"{'it mean':>7s} {'it max':>6s} {'full':>4s} {'max res':>8s} {'fail':>4s}  iterations")
        for v in args.variants:
            sim, reuse = runs[v]
            its = sim.cg_iterations[args.warm:]
            ms_step = 1e3 * statistics.median(times[v])
            mean = 1e3 * statistics.mean(times[v])
            row = {"case": case, "variant": v, "ms_per_step": ms_step, "ratio": ms_step / (1e3 * base),
                   "mean_ms_per_step": mean, "mean_ratio": mean / (1e3 * statistics.mean(times[args.variants[0]])),
                   "setup_ms": 1e3 * statistics.median(setup[v]), "iterations_mean": statistics.mean(its),
                   "iterations_max": max(its), "full_setups": reuse.full, "max_residual": max(residual[v]),
                   "cg_failures": sim.cg_failures, "iterations": its}
            rows.append(row)
            print(f"{v:>13s} {ms_step:8.1f} {row['ratio']:6.2f} {mean:8.1f} {row['mean_ratio']:6.2f} "
                  f"{row['setup_ms']:8.1f} {row['iterations_mean']:7.1f} {row['iterations_max']:6d} {reuse.full:4d} "
                  f"{row['max_residual']:8.1e} {sim.cg_failures:4d}  {' '.join(map(str, its))}", flush=True)
        for sim, _ in runs.values():
            sim.close()
        write_json(args.json, {"dt": 1 / 60, "precision": "f64", "cg_tol": 1e-6, "steps": args.steps,
                               "warm": args.warm, "rows": rows})  # after every case: long runs keep what they did
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
