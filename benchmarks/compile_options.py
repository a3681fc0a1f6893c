"""Taichi's advanced IR optimisation on and off, side by side in one run: compile time and step time.

Taichi compiles each kernel on its first launch; with ``advanced_optimization`` off it
skips its own (CHI IR) optimisation passes and hands the IR to LLVM, which still
optimises it. This measures what that costs and saves: the cold first step of the
32 x 32 cloth (Simulation built, kernels compiled with the offline cache off, one
step) per integrator, and the step or CG-iteration times of ``measure_case.py``.
Every measurement is a fresh process running ``measure_case.py`` with
``TI_ADVANCED_OPTIMIZATION`` set to 1 or 0 (Taichi's own switch; see
``massspring.device.ADVANCED_OPTIMIZATION`` for the project's default); the two
alternate, and which goes first alternates too, so drifting load hits both alike.
Reported: the median over ``--repeats`` processes, and off/on ratios.

    python benchmarks/compile_options.py
    python benchmarks/compile_options.py --cases cold-implicit-32 multigrid-128 --repeats 5
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

import output
from massspring.io.files import write_json

HERE = Path(__file__).resolve().parent
CASES = ["cold-implicit-32", "cold-symplectic-32", "cold-rk4-32", "cold-backward-euler-32", "implicit-32",
         "implicit-128", "multigrid-128", "symplectic-32", "symplectic-128", "explicit-128"]
SETTINGS = {"on": "1", "off": "0"}


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cases", nargs="+", default=CASES, choices=CASES, metavar="CASE",
                   help=f"default: all of {', '.join(CASES)}")
    p.add_argument("--repeats", type=int, default=3, help="processes per case and setting (default 3)")
    output.add_json(p, "compile_options")
    return p.parse_args(argv)


def measure(case, setting):
    env = dict(os.environ, TI_ADVANCED_OPTIMIZATION=SETTINGS[setting], TI_OFFLINE_CACHE="0")
    proc = subprocess.run([sys.executable, str(HERE / "measure_case.py"), case], capture_output=True, text=True,
                          env=env, timeout=1800)
    if proc.returncode != 0:
        raise SystemExit(f"{case} ({setting}) failed:\n{proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])["value"]


def main(argv=None):
    args = parse_args(argv)
    rows = []
    print(f"{'case':<24}{'unit':>6}{'on':>10}{'off':>10}{'off/on':>8}")
    for case in args.cases:
        values = {name: [] for name in SETTINGS}
        for k in range(args.repeats):
            order = list(SETTINGS) if k % 2 == 0 else list(SETTINGS)[::-1]
            for setting in order:
                values[setting].append(measure(case, setting))
        median = {name: statistics.median(v) for name, v in values.items()}
        unit = "s" if case.startswith("cold-") else "ms"
        ratio = median["off"] / median["on"]
        print(f"{case:<24}{unit:>6}{median['on']:>10.3f}{median['off']:>10.3f}{ratio:>8.2f}", flush=True)
        rows.append({"case": case, "unit": unit, "on": values["on"], "off": values["off"],
                     "median_on": median["on"], "median_off": median["off"], "ratio": ratio})
    write_json(args.json, {"repeats": args.repeats, "cases": rows})
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
