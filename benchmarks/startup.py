"""Time to first step of `massspring run SCENE`, with a cold and a warm Taichi offline cache.

Runs `python -m massspring run SCENE --steps 1 --quiet` in fresh processes for each
integrator: first with an empty offline cache (every kernel compiled), then again
with the cache it left (kernels loaded from disk). Reports the whole command's wall
time and the first step's time as the run summary gives it (it includes the
kernels' compilation or loading).

    python benchmarks/startup.py --help
    python benchmarks/startup.py --scene cloth
"""

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time

from massspring.io.files import write_json
import output


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", default="cloth")
    p.add_argument("--integrators", nargs="+", default=["implicit", "explicit", "symplectic"])
    p.add_argument("--warm-runs", type=int, default=3, help="warm-cache runs (median reported)")
    output.add_json(p, "startup")
    return p.parse_args(argv)


def run_once(scene, integrator, cache):
    env = dict(os.environ, TI_OFFLINE_CACHE_FILE_PATH=cache)
    t0 = time.perf_counter()
    out = subprocess.run([sys.executable, "-m", "massspring", "run", scene, "--integrator", integrator,
                          "--steps", "1", "--quiet"], capture_output=True, text=True, env=env)
    total = time.perf_counter() - t0
    if out.returncode:
        raise RuntimeError(out.stderr)
    step = float(re.search(r"in ([0-9.]+) s wall", out.stdout).group(1))
    return total, step


def main(argv=None):
    args = parse_args(argv)
    print(f"{'integrator':>10s} {'cold total s':>12s} {'cold step s':>11s} {'warm total s':>12s} {'warm step s':>11s}")
    rows = []
    for integrator in args.integrators:
        with tempfile.TemporaryDirectory() as cache:
            cold = run_once(args.scene, integrator, cache)
            warm = sorted(run_once(args.scene, integrator, cache) for _ in range(args.warm_runs))
            warm = warm[len(warm) // 2]
        row = {"scene": args.scene, "integrator": integrator, "cold_total_s": cold[0], "cold_step_s": cold[1],
               "warm_total_s": warm[0], "warm_step_s": warm[1]}
        rows.append(row)
        print(f"{integrator:>10s} {cold[0]:12.2f} {cold[1]:11.2f} {warm[0]:12.2f} {warm[1]:11.2f}", flush=True)
    write_json(args.json, rows)
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
