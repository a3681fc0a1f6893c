"""The drape with and without its strain limit, side by side in one run: the largest
spring stretch over the first second, CPU time per simulated second, and the strain
limit's iterations (issue 41's target: at most 10% at resolution 64 as shipped, at no
more than 1.5x the CPU time without the limit).

    python benchmarks/strain_limit.py [--resolution 64] [--integrators implicit ...] [--repeats 3]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import numpy as np

import output
from massspring.io.files import write_json


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", default="drape")
    p.add_argument("--resolution", type=int, default=64)
    p.add_argument("--duration", type=float, default=1.0, help="simulated seconds (default 1)")
    p.add_argument("--integrators", nargs="+", default=None, help="default: the scene's")
    p.add_argument("--repeats", type=int, default=3)
    output.add_json(p, "strain_limit")
    return p.parse_args(argv)


def run(scene, integrator, limit, duration):
    """One run: (CPU s, largest l / l0 - 1 after any step, iterations of each step)."""
    sim = scene.with_params(strain_limit=limit).simulation(integrator, tol=None)
    model = sim.model
    ends, l0 = model.springs, model.rest_lengths
    worst, iterations, cpu = 0.0, [], 0.0
    for _ in range(int(round(duration / sim.dt))):
        start = time.process_time()
        sim.step()
        cpu += time.process_time() - start
        x = sim.positions
        worst = max(worst, float((np.linalg.norm(x[ends[:, 1]] - x[ends[:, 0]], axis=1) / l0 - 1).max()))
        stats = sim.strain_limit_stats
        iterations.append(0 if stats is None else stats["iterations"])
    sim.close()
    return cpu, worst, iterations


def main(argv=None):
    args = parse_args(argv)
    import massspring as ms

    scene = ms.load_scene(args.scene).with_params(resolution=args.resolution)
    shipped = scene.model().strain_limit or 0.1
    rows = []
    print(f"{args.scene} {args.resolution}x{args.resolution}, {args.duration:g} s, median CPU of {args.repeats} "
          f"(limit {shipped:g} against none)")
    print(f"{'integrator':<16}{'limit':>7}{'CPU s':>9}{'stretch %':>11}{'iter. mean':>12}{'max':>6}{'ratio':>7}")
    for integrator in args.integrators or [scene.integrator]:
        for limit in (0.0, shipped):
            run(scene, integrator, limit, 2 * scene.default_dt(integrator))  # compiles
        cpu, seen = {0.0: [], shipped: []}, {}
        for _ in range(args.repeats):  # alternating, so that drifting load hits both alike
            for limit in (0.0, shipped):
                seconds, worst, iterations = run(scene, integrator, limit, args.duration)
                cpu[limit].append(seconds)
                seen[limit] = (worst, iterations)  # the same in every repeat (deterministic)
        base = statistics.median(cpu[0.0])
        for limit in (0.0, shipped):
            median = statistics.median(cpu[limit])
            worst, iterations = seen[limit]
            row = {"scene": args.scene, "resolution": args.resolution, "integrator": integrator, "limit": limit,
                   "duration_s": args.duration, "cpu_s": median, "cpu_samples": cpu[limit], "max_stretch": worst,
                   "iterations_mean": float(np.mean(iterations)), "iterations_max": int(max(iterations)),
                   "ratio": median / base}
            rows.append(row)
            print(f"{integrator:<16}{limit:>7g}{median:>9.2f}{100 * worst:>11.2f}"
                  f"{row['iterations_mean']:>12.1f}{row['iterations_max']:>6}{row['ratio']:>7.2f}")
    write_json(args.json, rows)
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
