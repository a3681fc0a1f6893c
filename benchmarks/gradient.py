"""Value and gradient against the forward run alone (``massspring.gradient``), side by side in one run.

For the ``cloth`` scene at ``--resolution`` (64: 4,096 particles, 24,192 springs) with
each differentiable integrator at its suggested dt (half the predicted stability limit
for the explicit ones, 1/60 s for the implicit step, whose default preconditioner at
this size is multigrid): the median wall time of ``--steps``
forward steps (a Simulation stepped, as a user runs it) and of the value and gradient
of an objective of the last frame in stiffness, damping, rest lengths, masses and the
initial state (the forward pass, the checkpointed stretches run again, the backward
pass), each after one untimed warm-up run (compiles excluded), and their ratio. Then,
in a child process, the peak resident memory of a symplectic gradient over ``--long``
steps against that of a forward run of the same length.

With ``--scene`` another scene (at the same dt; ``--set key=value``
changes its parameters as the CLI's ``--set`` does), e.g. the cloth draping over a
sphere with friction, contact and friction in every step's gradient:

    python benchmarks/gradient.py
    python benchmarks/gradient.py --resolution 32 --steps 100 --long 1000
    python benchmarks/gradient.py --scene drape --set strain_limit=0 --resolution 32 --integrators implicit \
        --solved-steps 60 --long 0 --json benchmarks/out/gradient_drape.json
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time

import output
from massspring.support.errors import GradientError
from massspring.io.files import write_json

CHILD = """
import json, resource, sys, time
import numpy as np
import massspring as ms
resolution, steps, integrator, what = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3], sys.argv[4]
scene = ms.load_scene("cloth").with_params(resolution=resolution)
model = scene.model()
from massspring.analysis.stability import predict
from massspring.integrators import INTEGRATORS
dt = INTEGRATORS[integrator].suggest_dt(predict(model))
def last_height(frames):
    partial = np.zeros_like(frames.positions)
    partial[-1, :, 2] = 1.0
    return float(frames.positions[-1, :, 2].sum()), {"positions": partial}
start = time.perf_counter()
if what == "forward":
    ms.Simulation(model, integrator, dt=dt).step(steps).close()
else:
    ms.gradient(model, last_height, ["stiffness", "positions"], steps=steps, every=steps, integrator=integrator, dt=dt)
print(json.dumps({"wall_s": time.perf_counter() - start,
                  "peak_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6}))
"""


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", default="cloth", help="a built-in scene (default cloth)")
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
                   help="a scene parameter (a JSON value or a word), repeatable")
    p.add_argument("--resolution", type=int, default=64)
    p.add_argument("--steps", type=int, default=200, help="steps of the timed explicit runs (default 200)")
    p.add_argument("--solved-steps", type=int, default=20,
                   help="steps of the timed runs of integrators that solve a system (default 20)")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--long", type=int, default=10_000,
                   help="steps of the memory runs, symplectic only (default 10,000; 0: none)")
    p.add_argument("--integrators", nargs="+", default=None, help="default: every differentiable one")
    output.add_json(p, "gradient")
    return p.parse_args(argv)


def last_height(frames):
    """L = the sum of the last frame's heights (m)."""
    partial = frames.positions * 0
    partial[-1, :, 2] = 1.0
    return float(frames.positions[-1, :, 2].sum()), {"positions": partial}


def scene_params(args):
    """``--resolution`` and the ``--set`` pairs as the scene's parameters."""
    params = {"resolution": args.resolution}
    for pair in args.sets:
        key, _, value = pair.partition("=")
        try:
            params[key] = json.loads(value)
        except json.JSONDecodeError:
            params[key] = value
    return params


def timed(args, integrator):
    import massspring as ms
    from massspring.analysis.stability import predict
    from massspring.integrators import INTEGRATORS

    scene = ms.load_scene(args.scene).with_params(**scene_params(args))
    model = scene.model()
    dt = INTEGRATORS[integrator].suggest_dt(predict(model))
    names = ["stiffness", "damping", "rest_lengths", "masses", "positions", "velocities"]
    steps = args.solved_steps if INTEGRATORS[integrator].traits.linear_solver else args.steps

    def forward():
        ms.Simulation(model, integrator, dt=dt).step(steps).close()

    def backward():
        ms.gradient(model, last_height, names, steps=steps, every=steps, integrator=integrator, dt=dt)

    times = {"forward": [], "gradient": []}
    for run in (forward, backward):
        run()  # compiles
    for _ in range(args.repeats):  # alternating, so that drifting load hits both alike
        for name, run in (("forward", forward), ("gradient", backward)):
            start = time.perf_counter()
            run()
            times[name].append(time.perf_counter() - start)
    return dt, steps, {name: statistics.median(values) for name, values in times.items()}


def child(args, integrator, what):
    proc = subprocess.run([sys.executable, "-c", CHILD, str(args.resolution), str(args.long), integrator, what],
                          capture_output=True, text=True, timeout=3600)
    if proc.returncode != 0:
        raise SystemExit(f"{integrator} {what} failed:\n{proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main(argv=None):
    args = parse_args(argv)
    from massspring.gradients import differentiable

    integrators = args.integrators or list(differentiable())
    rows = []
    print(f"{args.scene} {args.resolution}x{args.resolution} {' '.join(args.sets)}, median of {args.repeats}")
    print(f"{'integrator':<12}{'dt s':>10}{'steps':>7}{'forward s':>11}{'gradient s':>12}{'ratio':>7}")
    for integrator in integrators:
        try:
            dt, steps, med = timed(args, integrator)
        except GradientError as error:  # a limit of the adjoint solve, recorded (docs/gradients.md)
            print(f"{integrator:<12}{error}")
            rows.append({"integrator": integrator, "resolution": args.resolution, "error": str(error)})
            continue
        row = {"integrator": integrator, "scene": args.scene, "sets": args.sets, "resolution": args.resolution,
               "steps": steps, "dt": dt,
               "forward_s": med["forward"], "gradient_s": med["gradient"], "ratio": med["gradient"] / med["forward"]}
        print(f"{integrator:<12}{dt:>10.2e}{steps:>7}{med['forward']:>11.3f}{med['gradient']:>12.3f}"
              f"{row['ratio']:>7.2f}")
        if args.long and integrator == "symplectic":
            row["long_steps"] = args.long
            for what in ("forward", "gradient"):
                out = child(args, integrator, what)
                row[f"long_{what}_s"], row[f"long_{what}_peak_gb"] = out["wall_s"], out["peak_gb"]
            print(f"{'':<12}{args.long:,} steps: forward {row['long_forward_s']:.1f} s, peak "
                  f"{row['long_forward_peak_gb']:.2f} GB; gradient {row['long_gradient_s']:.1f} s, peak "
                  f"{row['long_gradient_peak_gb']:.2f} GB")
        rows.append(row)
    write_json(args.json, {"rows": rows, "peak_rss_gb_this_process": resource.getrusage(
        resource.RUSAGE_SELF).ru_maxrss / 1e6})
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
