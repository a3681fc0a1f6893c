"""What an error-controlled try costs on small systems, against a fixed-dt step.

Per scene and integrator: an error-controlled run (``tol``, horizon T) from 1 ms into
it to T, wall time per try (accepted or rejected), median of ``--repeats`` runs; and a
fixed-dt run at the scene's dt, wall time per step over ``--fixed-steps`` steps after
5 warm-up steps. The difference is the adaptive run's own per-try work: the state (and
what the integrator carries from step to step) read back to the host, the estimate in
numpy, the controller, the per-step solver tolerances. Kernels are compiled by a run
before the timed ones.

It imports the installed massspring unless the repository root comes first on the path,
so running it against another checkout (``PYTHONPATH=/path/to/checkout python
benchmarks/adaptive_overhead.py``) compares two versions on the same machine::

    python benchmarks/adaptive_overhead.py
    python benchmarks/adaptive_overhead.py --cases rope-drop/implicit chain/bdf2 --repeats 5
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import output  # noqa: E402

import massspring as ms  # noqa: E402
from massspring.io.files import write_json  # noqa: E402

CASES = {"rope-drop/implicit": 0.2, "chain/bdf2": 0.3, "chain/midpoint": 0.3, "chain/backward-euler": 0.3,
         "spring/symplectic": 0.5}


def parse(argv):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cases", nargs="+", default=list(CASES), help="scene/integrator (default: %(default)s)")
    p.add_argument("--tol", type=float, default=1e-3)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--fixed-steps", type=int, default=200)
    output.add_json(p, "adaptive_overhead")
    return p.parse_args(argv)


def adaptive_try(scene, integrator, tol, horizon):
    """(wall s per try, tries) of an error-controlled run from 1 ms to ``horizon``."""
    sim = scene.simulation(integrator, tol=tol, horizon=horizon)
    sim.advance(1e-3)
    before = sim.control_stats()
    start = time.perf_counter()
    sim.advance(horizon - 1e-3)
    wall = time.perf_counter() - start
    after = sim.control_stats()
    tries = after["accepted"] - before["accepted"] + sum(after["rejected"].values()) - sum(before["rejected"].values())
    return wall / tries, tries


def fixed_step(scene, integrator, steps):
    """Wall s per step of a fixed-dt run at the scene's dt, after 5 steps."""
    sim = scene.simulation(integrator, tol=None)
    sim.step(5)
    start = time.perf_counter()
    sim.step(steps)
    return (time.perf_counter() - start) / steps


def main(argv=None):
    args = parse(argv)
    rows = {}
    print(f"{'case':24s} {'tries':>6s} {'ms/try':>8s} {'ms/fixed step':>14s} {'ratio':>6s}")
    for case in args.cases:
        name, integrator = case.split("/")
        scene = ms.load_scene(name)
        horizon = CASES.get(case, 0.3)
        adaptive_try(scene, integrator, args.tol, horizon)  # compiles
        runs = [adaptive_try(scene, integrator, args.tol, horizon) for _ in range(args.repeats)]
        per_try = statistics.median(r[0] for r in runs)
        fixed = statistics.median(fixed_step(scene, integrator, args.fixed_steps) for _ in range(args.repeats))
        rows[case] = {"tol": args.tol, "horizon": horizon, "tries": runs[0][1], "ms_per_try": per_try * 1e3,
                      "ms_per_fixed_step": fixed * 1e3, "ratio": per_try / fixed}
        print(f"{case:24s} {runs[0][1]:6d} {per_try * 1e3:8.3f} {fixed * 1e3:14.4f} {per_try / fixed:6.1f}")
    write_json(args.json, {"repeats": args.repeats, "cases": rows})
    print(f"\nwrote {args.json}")


if __name__ == "__main__":
    main()
