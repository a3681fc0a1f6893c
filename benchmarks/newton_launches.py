"""Newton-solved steps on small systems: the iteration in one launch against the loop driven from Python.

On a small system (serial loops, a pointwise preconditioner) a Newton-solved step is
launch-bound: the loop of ``BackwardEuler._newton`` launches one kernel per CG solve,
direction, line-search trial and refresh. ``kernels/newton.py::newton_solve`` runs the
same iteration in one launch (the same bits: ``tests/test_newton.py``); a run takes it
after ``ONE_LAUNCH_AFTER`` tries, as it costs more to compile. Per case
(scene/integrator), side by side in one run, each mode in its own processes (the
processes alternate, and which mode goes first alternates too):

* ``fixed``: ms per step of a fixed-dt run at the scene's dt over ``--steps`` steps,
  after 5 steps that compile the kernels;
* ``adaptive``: ms per try of an error-controlled run (tol ``--tol``) over the case's
  horizon, after a run that compiles the kernels;
* ``compile``: s to build the simulation and take its first step with Taichi's offline
  cache off (the cold compile).

Modes: ``loop`` (``ONE_LAUNCH_AFTER`` = 10^9: never) and ``one`` (0: from the first try).
Printed: medians of ``--repeats`` processes and the ratios loop / one::

    python benchmarks/newton_launches.py
    python benchmarks/newton_launches.py --cases chain/bdf2 --repeats 5
"""

from __future__ import annotations

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

sys.path.insert(1, str(Path(__file__).resolve().parents[1]))
from massspring.io.files import write_json  # noqa: E402

CASES = {"chain/backward-euler": 0.3, "chain/bdf2": 0.3, "chain/midpoint": 0.3, "stiffchain/backward-euler": 0.2,
         "stiffchain/bdf2": 0.2, "rope-drop/bdf2": 0.2}
MODES = {"loop": 10**9, "one": 0}


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES), metavar="CASE",
                   help="scene/integrator (default: %(default)s)")
    p.add_argument("--steps", type=int, default=300, help="timed fixed-dt steps (default 300)")
    p.add_argument("--tol", type=float, default=1e-3, help="the error-controlled runs' tol (default 1e-3)")
    p.add_argument("--repeats", type=int, default=3, help="processes per case and mode (default 3)")
    p.add_argument("--child", nargs=3, metavar=("CASE", "MODE", "WHAT"), help=argparse.SUPPRESS)
    output.add_json(p, "newton_launches")
    return p.parse_args(argv)


def child(case, mode, what, steps, tol):
    """One measurement in this process: returns ms per step or try, or s to the first step."""
    import massspring as ms
    from massspring.integrators import newton

    newton.ONE_LAUNCH_AFTER = MODES[mode]
    name, integrator = case.split("/")
    scene = ms.load_scene(name)
    if what == "compile":
        start = time.perf_counter()
        scene.simulation(integrator, tol=None).step(1)
        return time.perf_counter() - start
    if what == "fixed":
        sim = scene.simulation(integrator, tol=None)
        sim.step(5)
        start = time.perf_counter()
        sim.step(steps)
        return (time.perf_counter() - start) / steps * 1e3
    horizon = CASES[case]
    scene.simulation(integrator, tol=tol, horizon=horizon).advance(horizon)  # compiles
    sim = scene.simulation(integrator, tol=tol, horizon=horizon)
    start = time.perf_counter()
    sim.advance(horizon)
    stats = sim.control_stats()
    return (time.perf_counter() - start) / (stats["accepted"] + sum(stats["rejected"].values())) * 1e3


def measure(case, mode, what, args):
    env = dict(os.environ)
    if what == "compile":
        env["TI_OFFLINE_CACHE"] = "0"
    proc = subprocess.run([sys.executable, __file__, "--child", case, mode, what, "--steps", str(args.steps),
                           "--tol", str(args.tol)], capture_output=True, text=True, env=env, timeout=1800)
    if proc.returncode != 0:
        raise SystemExit(f"{case} {mode} {what} failed:\n{proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main(argv=None):
    args = parse_args(argv)
    if args.child:
        print(json.dumps(child(*args.child, args.steps, args.tol)))
        return
    rows = []
    print(f"{'case':<28}{'measure':>9}{'loop':>10}{'one':>10}{'loop/one':>10}")
    for case in args.cases:
        for what, unit in (("fixed", "ms/step"), ("adaptive", "ms/try"), ("compile", "s")):
            values = {mode: [] for mode in MODES}
            for k in range(args.repeats):
                for mode in (list(MODES) if k % 2 == 0 else list(MODES)[::-1]):
                    values[mode].append(measure(case, mode, what, args))
            median = {mode: statistics.median(v) for mode, v in values.items()}
            ratio = median["loop"] / median["one"]
            print(f"{case:<28}{what:>9}{median['loop']:>10.3f}{median['one']:>10.3f}{ratio:>10.2f}  {unit}",
                  flush=True)
            rows.append({"case": case, "measure": what, "unit": unit, "values": values, "median": median,
                         "loop_over_one": ratio})
    write_json(args.json, {"steps": args.steps, "tol": args.tol, "repeats": args.repeats, "rows": rows})
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
