"""A sweep in one process against the same sweep on local Dask workers.

The sweep: ``--cases`` stiffness values of a ``chain`` of ``--count`` particles,
implicit, ``--steps`` steps each (about 1 s of wall time per case here with the
defaults). It runs serially in this process (kernels compiled beforehand), then, for
each of ``--workers``: as the command a user types, serial and with ``--workers N``,
each in a new process (process start, Taichi's start and compilation included); and
in this process as ``massspring sweep --workers N`` does: the clock starts before the
local cluster is started and stops after it is shut down (startup, each worker's
compilation and the shutdown included). Every row's figures must be the same
bits as the serial one's. Then the overhead per task on a warm worker: the same
cases on one warmed-up worker, the elapsed time minus the time the cases report
inside the worker, per case.

    python benchmarks/sweep.py
    python benchmarks/sweep.py --workers 1 2 --cases 12
    python benchmarks/sweep.py --json benchmarks/results/sweep.json
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
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
    p.add_argument("--count", type=int, default=400, help="chain particles (default 400)")
    p.add_argument("--steps", type=int, default=300, help="implicit steps per case (default 300)")
    p.add_argument("--cases", type=int, default=12, help="stiffness values (default 12)")
    p.add_argument("--workers", nargs="+", type=int, default=[2], help="local cluster sizes (default 2)")
    output.add_json(p, "sweep")
    return p.parse_args(argv)


def command(args, vary, where):
    """Wall time of `massspring sweep` in a new process (serial, or ``where`` = --workers N)."""
    with tempfile.TemporaryDirectory() as tmp:
        argv = [sys.executable, "-m", "massspring", "sweep", "chain", "--set", f"count={args.count}", "--integrator",
                "implicit", "--steps", str(args.steps), "--vary", "stiffness=" + ",".join(map(str, vary["stiffness"])),
                "--out", str(Path(tmp) / "s.csv"), "--quiet", *where]
        start = time.perf_counter()
        subprocess.run(argv, check=True, capture_output=True)
        wall = time.perf_counter() - start
    return {"workers": int(where[1]) if where else 0, "command": True, "wall_s": wall}


def main(argv=None):
    args = parse_args(argv)
    scene = ms.load_scene("chain").with_params(count=args.count)
    vary = {"stiffness": [1000.0 + 100.0 * k for k in range(args.cases)]}
    options = dict(integrator="implicit", steps=args.steps)
    ms.sweep(scene, {"stiffness": [1000.0]}, integrator="implicit", steps=1)  # compile here first
    start = time.perf_counter()
    serial = ms.sweep(scene, vary, **options)
    serial_wall = time.perf_counter() - start
    case_wall = statistics.median(r["wall_s"] for r in serial)
    print(f"chain of {args.count}, {args.cases} cases of {args.steps} implicit steps ({case_wall:.2f} s each, "
          f"median), {os.cpu_count()} CPUs")
    print(f"{'where':>10s} {'wall s':>8s} {'speed-up':>9s} {'same bits':>9s}")
    print(f"{'serial':>10s} {serial_wall:8.2f} {1.0:9.2f}")
    rows = [{"workers": 0, "wall_s": serial_wall, "speedup": 1.0, "same": True}]
    for workers in args.workers:
        for where in ([], ["--workers", str(workers)]):  # the command as a user runs it, process start included
            rows.append(command(args, vary, where))
            print(f"{'command' + (f' --workers {workers}' if where else ''):>10s} {rows[-1]['wall_s']:8.2f} "
                  f"{rows[-1 - (1 if where else 0)]['wall_s'] / rows[-1]['wall_s'] if where else 1.0:9.2f}",
                  flush=True)
        start = time.perf_counter()
        with cluster.cluster(workers=workers) as client:
            there = ms.sweep(scene, vary, client=client, **options)
        wall = time.perf_counter() - start
        same = [[r[k] for k in FIGURES] for r in there] == [[r[k] for k in FIGURES] for r in serial]
        rows.append({"workers": workers, "wall_s": wall, "speedup": serial_wall / wall, "same": same})
        print(f"{f'{workers} workers':>10s} {wall:8.2f} {serial_wall / wall:9.2f} {'yes' if same else 'NO':>9s}",
              flush=True)
    with cluster.cluster(workers=1) as client:
        ms.sweep(scene, {"stiffness": [1000.0]}, client=client, **options)  # warm the worker up
        start = time.perf_counter()
        warm = ms.sweep(scene, vary, client=client, **options)
        elapsed = time.perf_counter() - start
    overhead = (elapsed - sum(r["wall_s"] for r in warm)) / len(warm)
    print(f"\noverhead per task on a warm worker: {overhead * 1e3:.1f} ms, {overhead / case_wall:.1%} of a "
          f"{case_wall:.2f} s case")
    write_json(args.json, {"count": args.count, "steps": args.steps, "cases": args.cases, "case_s": case_wall,
                           "cpus": os.cpu_count(), "rows": rows, "task_overhead_s": overhead,
                           "task_overhead_fraction": overhead / case_wall})
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
