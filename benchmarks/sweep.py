"""A sweep in one process against the same sweep on a local Dask cluster.

Runs ``--cases`` stiffness values of the ``cloth`` scene (``--resolution``, implicit,
``--steps`` steps each) serially in this process, then on local clusters of each of
``--workers`` worker processes (started before the clock starts, closed after), and
prints the wall time of each, its speed-up over the serial run and whether every
row's figures are the same bits. Taichi's threads per process are left at their
default, so on a machine with few cores the workers share them.

    python benchmarks/sweep.py
    python benchmarks/sweep.py --workers 1 2 4 --cases 16
    python benchmarks/sweep.py --json benchmarks/results/sweep.json
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import output  # noqa: E402

import massspring as ms  # noqa: E402
from massspring.analysis import cluster, sweep  # noqa: E402
from massspring.io.files import write_json  # noqa: E402

FIGURES = ("status", "steps", "energy", "max_strain", "cg_iterations")


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--resolution", type=int, default=32)
    p.add_argument("--steps", type=int, default=120, help="implicit steps of 1/60 s per case (default 120)")
    p.add_argument("--cases", type=int, default=8, help="stiffness values, 1e3 to 1e5 (default 8)")
    p.add_argument("--workers", nargs="+", type=int, default=[2], help="cluster sizes to time (default 2)")
    output.add_json(p, "sweep")
    return p.parse_args(argv)


def main(argv=None):
    args = parse_args(argv)
    scene = ms.load_scene("cloth").with_params(resolution=args.resolution)
    vary = {"stiffness": [float(f"{1e3 * 100 ** (k / max(1, args.cases - 1)):.4g}") for k in range(args.cases)]}
    sweep.sweep(scene, {"stiffness": vary["stiffness"][:1]}, integrator="implicit", steps=1)  # compile here
    start = time.perf_counter()
    serial = sweep.sweep(scene, vary, integrator="implicit", steps=args.steps)
    wall = time.perf_counter() - start
    rows = [{"workers": 0, "wall_s": wall, "speedup": 1.0, "same": True}]
    print(f"cloth {args.resolution}x{args.resolution}, {args.cases} cases of {args.steps} implicit steps, "
          f"{os.cpu_count()} CPUs")
    print(f"{'where':>12s} {'wall s':>8s} {'speed-up':>9s} {'same bits':>9s}")
    print(f"{'serial':>12s} {wall:8.2f} {1.0:9.2f} {'':>9s}")
    for workers in args.workers:
        with cluster.cluster(workers=workers) as client:
            start = time.perf_counter()
            there = sweep.sweep(scene, vary, integrator="implicit", steps=args.steps, client=client)
            wall = time.perf_counter() - start
        same = [[r[k] for k in FIGURES] for r in there] == [[r[k] for k in FIGURES] for r in serial]
        rows.append({"workers": workers, "wall_s": wall, "speedup": rows[0]["wall_s"] / wall, "same": same})
        print(f"{f'{workers} workers':>12s} {wall:8.2f} {rows[-1]['speedup']:9.2f} {'yes' if same else 'NO':>9s}",
              flush=True)
    write_json(args.json, {"resolution": args.resolution, "steps": args.steps, "cases": args.cases,
                           "cpus": os.cpu_count(), "rows": rows})
    print(f"\nwrote {args.json}")


if __name__ == "__main__":
    main()
