"""What one Taichi kernel launch costs on this CPU, serial against parallel loops.

For loops of ``--sizes`` elements (a[i] = 0.5 a[i] + 1, f64), times one launch of a
kernel whose loop is serial (``ti.loop_config(serialize=True)``) and of the same
kernel with Taichi's parallel loop, with every thread of the machine and with one.
Printed and written: microseconds per launch (median of ``--repeats`` runs of
``--launches`` launches). The difference at a small size is what a parallel phase
costs before it does any work; ``simulation.SERIAL_BELOW`` and multigrid's
``serial_below`` are set where two threads save more than that (``switch_point.py``).

    python benchmarks/launch_cost.py
    python benchmarks/launch_cost.py --sizes 1000 100000 --launches 500
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import output  # noqa: E402

from massspring.io.files import write_json  # noqa: E402


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[1_000, 100_000, 1_000_000])
    p.add_argument("--launches", type=int, default=200, help="launches per timed run")
    p.add_argument("--repeats", type=int, default=5, help="timed runs per case (median reported)")
    p.add_argument("--threads", type=int, default=None, help=argparse.SUPPRESS)  # the child's thread count
    output.add_json(p, "launch_cost")
    return p.parse_args(argv)


def measure(sizes, launches, repeats, threads):
    """{size: {"serial": us, "parallel": us}} in this process, Taichi on ``threads`` threads."""
    import taichi as ti
    ti.init(arch=ti.cpu, cpu_max_num_threads=threads, log_level=ti.ERROR, offline_cache=False)
    result = {}
    for n in sizes:
        a = ti.field(ti.f64, n)

        @ti.kernel
        def serial():
            ti.loop_config(serialize=True)
            for i in range(n):
                a[i] = 0.5 * a[i] + 1.0

        @ti.kernel
        def parallel():
            for i in range(n):
                a[i] = 0.5 * a[i] + 1.0

        row = {}
        for name, kernel in (("serial", serial), ("parallel", parallel)):
            kernel()  # compile
            runs = []
            for _ in range(repeats):
                t0 = time.perf_counter()
                for _ in range(launches):
                    kernel()
                runs.append((time.perf_counter() - t0) / launches)
            row[name] = 1e6 * statistics.median(runs)
        result[n] = row
    return result


def main(argv=None):
    args = parse_args(argv)
    if args.threads is not None:  # a child: one thread count per process (Taichi starts once)
        print(json.dumps(measure(args.sizes, args.launches, args.repeats, args.threads)))
        return 0
    cores = os.cpu_count() or 1
    rows = []
    print(f"{'elements':>10s} {'threads':>7s} {'serial us':>10s} {'parallel us':>12s}")
    for threads in sorted({cores, 1}, reverse=True):
        command = [sys.executable, __file__, "--threads", str(threads), "--launches", str(args.launches),
                   "--repeats", str(args.repeats), "--sizes", *map(str, args.sizes)]
        done = subprocess.run(command, capture_output=True, text=True, check=True)
        for n, row in json.loads(done.stdout.strip().splitlines()[-1]).items():
            n = int(n)
            rows.append({"elements": n, "threads": threads, "serial_us": row["serial"],
                         "parallel_us": row["parallel"]})
            print(f"{n:10d} {threads:7d} {row['serial']:10.1f} {row['parallel']:12.1f}", flush=True)
    write_json(args.json, {"cpu_count": cores, "launches": args.launches, "rows": rows})
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
