"""Newton's and CG's tolerances taken from the requested error (issue 62): what they
cost and what they keep, against the fixed ``newton_tol`` of a fixed-dt run.

1. cloth: the ``cloth`` scene at ``--resolution`` (stiffness 1e4, multigrid, as
   ``benchmarks/newton.py``'s tolerance table) over ``--duration`` s, backward Euler and
   BDF2: at the frame rate dt 1/60 s with ``newton_tol`` 1e-3 (the default, kept for the
   stiff chain) and 1e-2, and error-controlled at each of ``--tols`` with steps of at most
   1/60 s (``max_dt``): steps, Newton iterations a step, wall time, the derived
   newton_tol (median over the steps) and the end error: RMS position distance of the
   moving particles from a reference (the same integrator at dt 1/480 s, newton_tol
   1e-8) over the scene's size, as the study measures it;
2. stiffchain: the shipped undamped ``stiffchain`` (ks 1e6 N/m) over ``--chain-duration``
   s, BDF2 and the midpoint rule error-controlled at 1e-6: the derived newton_tol (the
   smallest and the median), the Newton residual each step ended at (the largest,
   relative to its warm start) and the end error against RK4 at dt 1e-6 s.

    python benchmarks/derived_tolerances.py --resolution 64
    python benchmarks/derived_tolerances.py --json benchmarks/results/derived_tolerances.json
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import output  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import massspring as ms  # noqa: E402
from massspring.engine.adaptive import scene_size  # noqa: E402

FRAME = 1 / 60


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--resolution", type=int, default=128)
    p.add_argument("--duration", type=float, default=10 * FRAME, help="cloth: simulated seconds (default 10 frames)")
    p.add_argument("--tols", default="1e-2,1e-3", help="cloth: the error-controlled runs' tolerances")
    p.add_argument("--chain-duration", type=float, default=0.05)
    output.add_json(p, "derived_tolerances")
    return p.parse_args(argv)


def end_error(sim, reference, moving, size) -> float:
    d = sim.positions[moving] - reference[moving]
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1)))) / size


def tracked(sim, until):
    """Step ``sim`` to time ``until`` one accepted step at a time: (wall s, the Newton
    tolerance each step was solved to, the Newton residual each ended at)."""
    tols, residuals = [], []
    start = time.perf_counter()
    if sim.tol is None:
        for _ in range(round(until / sim.dt)):
            sim.step(1)
            tols.append(sim.stepper.newton_tol)
            residuals.append(sim.stepper.stats.newton_residual)
    else:
        while sim.time < until:
            if sim.time + 2 * sim.control_stats()["next_dt"] < until:
                sim.step(1)  # one accepted step
            else:
                sim.advance(until - sim.time)  # the last one or two, landing on until
            tols.append(sim.stepper.newton_tol)
            residuals.append(sim.stepper.stats.newton_residual)
    return time.perf_counter() - start, tols, residuals


def cloth_table(resolution, duration, tols):
    scene = ms.load_scene("cloth").with_params(resolution=resolution, stiffness=1e4)
    model = scene.model()
    moving, size = np.flatnonzero(model.free_mask()), scene_size(model)
    rows = []
    for integrator in ("backward-euler", "bdf2"):
        sim = scene.simulation(integrator, dt=FRAME / 8, preconditioner="multigrid", newton_tol=1e-8)
        sim.step(round(duration / sim.dt))
        reference = sim.positions
        sim.close()
        runs = [("fixed", dict(dt=FRAME, newton_tol=1e-3)), ("fixed", dict(dt=FRAME, newton_tol=1e-2))]
        runs += [("tol", dict(dt=FRAME, tol=tol, max_dt=FRAME, horizon=duration)) for tol in tols]
        for kind, options in runs:
            sim = scene.simulation(integrator, preconditioner="multigrid", **options)
            wall, used, residuals = tracked(sim, duration)
            row = {"integrator": integrator, "kind": kind, "resolution": resolution, "duration_s": duration,
                   "tol": options.get("tol"), "newton_tol": options.get("newton_tol"), "steps": sim.steps,
                   "newton_per_step": float(np.mean(sim.newton_iterations)), "wall_s": wall,
                   "derived_newton_tol_median": statistics.median(used) if kind == "tol" else None,
                   "end_error": end_error(sim, reference, moving, size)}
            rows.append(row)
            print(f"{integrator:15s} {kind:5s} tol {str(row['tol']):6s} newton_tol {str(row['newton_tol']):6s} "
                  f"steps {row['steps']:4d}  Newton/step {row['newton_per_step']:5.2f}  wall {wall:7.2f} s  "
                  f"derived {row['derived_newton_tol_median'] or float('nan'):.2g}  end error {row['end_error']:.3g}",
                  flush=True)
            sim.close()
    return rows


def chain_table(duration):
    scene = ms.load_scene("stiffchain")
    model = scene.model()
    moving, size = np.flatnonzero(model.free_mask()), scene_size(model)
    sim = scene.simulation("rk4", dt=1e-6)
    sim.step(round(duration / 1e-6))
    reference = sim.positions
    sim.close()
    rows = []
    for integrator in ("bdf2", "midpoint"):
        sim = scene.simulation(integrator, dt=1e-4, tol=1e-6, horizon=duration)
        wall, used, residuals = tracked(sim, duration)
        row = {"integrator": integrator, "tol": 1e-6, "duration_s": duration, "steps": sim.steps, "wall_s": wall,
               "derived_newton_tol_min": min(used), "derived_newton_tol_median": statistics.median(used),
               "newton_residual_max": max(residuals), "newton_per_step": float(np.mean(sim.newton_iterations)),
               "end_error": end_error(sim, reference, moving, size)}
        rows.append(row)
        print(f"stiffchain {integrator:9s} tol 1e-6: steps {row['steps']}, wall {wall:.2f} s, derived newton_tol "
              f"{row['derived_newton_tol_min']:.2g}..{row['derived_newton_tol_median']:.2g} (min..median), Newton "
              f"residual at most {row['newton_residual_max']:.2g}, Newton/step {row['newton_per_step']:.2f}, "
              f"end error {row['end_error']:.3g}", flush=True)
        sim.close()
    return rows


def main(argv=None):
    args = parse_args(argv)
    tols = [float(t) for t in args.tols.split(",")]
    result = {"cloth": cloth_table(args.resolution, args.duration, tols), "stiffchain": chain_table(args.chain_duration)}
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(result, indent=1))
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
