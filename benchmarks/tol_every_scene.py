"""Every shipped scene x integrator at a tolerance: does an error-controlled run get
through where the scene's fixed default dt does not?

For each scene (its default size) and each integrator: the fixed-dt run at the scene's
default dt for that integrator, then the error-controlled run (``tol``, ``horizon`` the
end time), both to the end time T (default the study's, a tenth of the scene's
duration), each stopped past ``--budget`` CPU seconds (compiling the kernels counted in
the first run of a configuration, the fixed one: a fixed run "over budget at t = 0 s"
spent it compiling). Each run's outcome: "ok" (steps,
rejections), "diverged" (``DivergenceError`` of the fixed run; ``StepSizeError`` of the
error-controlled one, exit 3 at the command line) or "over budget" (the time reached).
The target (issue 62): no error-controlled run stops with ``StepSizeError`` where the
fixed default dt diverges.

    PYTHONPATH=. python benchmarks/tol_every_scene.py --json benchmarks/results/tol_every_scene.json
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import adaptive  # noqa: E402
import output  # noqa: E402

import massspring as ms  # noqa: E402
from massspring.analysis import study  # noqa: E402
from massspring.device import reset_taichi  # noqa: E402
from massspring.integrators import INTEGRATORS  # noqa: E402
from massspring.io.files import write_json  # noqa: E402
from massspring.scene import builtin_scenes  # noqa: E402

TOL = 1e-3
BUDGET = 10.0  # CPU s a run


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", nargs="+", default=sorted(builtin_scenes()))
    p.add_argument("--integrators", nargs="+", default=list(INTEGRATORS), choices=list(INTEGRATORS))
    p.add_argument("--tol", type=float, default=TOL, help=f"the error-controlled runs' tolerance (default {TOL:g})")
    p.add_argument("--fraction", type=float, default=None,
                   help="end time as a fraction of the scene's duration (default: the study's end time)")
    p.add_argument("--budget", type=float, default=BUDGET, help=f"CPU s a run before it is stopped (default {BUDGET:g})")
    output.add_json(p, "tol_every_scene")
    return p.parse_args(argv)


def attempt(make, end, budget):
    """Outcome of running the Simulation ``make()`` to ``end`` s: a dict with ``outcome``
    ("ok", "diverged", "over budget"), ``time`` reached (s), CPU s, steps and, for an
    error-controlled run, its rejections; ``error``, the message of a divergence."""
    sim = make()
    row = {}
    try:
        cpu, _, _ = adaptive.timed(lambda: sim.advance(end), budget)
        row.update(outcome="ok", cpu_s=cpu)
    except adaptive.OverBudget:
        row.update(outcome="over budget", cpu_s=budget)
    except ms.DivergenceError as error:
        row.update(outcome="diverged", error=adaptive.message(error))
    except Exception as error:  # the alarm went off while Taichi compiled: it re-raises its own error
        if "OverBudget" not in str(error):
            raise
        row.update(outcome="over budget", cpu_s=budget, time=sim.time, steps=sim.steps)
        reset_taichi()  # the interrupted compile leaves nothing half-made behind
        return row
    row.update(time=sim.time, steps=sim.steps)
    stats = sim.control_stats()
    if stats is not None:
        row["rejected"] = sum(stats["rejected"].values())
    adaptive.close(sim)
    return row


def cell(row):
    if row["outcome"] == "ok":
        rejected = f", {row['rejected']} rejected" if "rejected" in row else ""
        return f"ok ({row['steps']} steps{rejected})"
    return f"{row['outcome']} at t = {row['time']:.4g} s"


def main(argv=None):
    args = parse_args(argv)
    rows = []
    print(f"{'scene':<12}{'integrator':<16}{'fixed default dt':<36}tol {args.tol:g}")
    for name in args.scenes:
        scene = ms.load_scene(name)
        end = study.default_duration(scene) if args.fraction is None else args.fraction * scene.duration
        for integrator in args.integrators:
            dt = scene.default_dt(integrator)
            fixed = attempt(lambda: scene.simulation(integrator, tol=None), round(end / dt) * dt, args.budget)
            controlled = attempt(lambda: scene.simulation(integrator, tol=args.tol, horizon=end), end, args.budget)
            rows.append({"scene": name, "integrator": integrator, "end_s": end, "dt": dt, "fixed": fixed,
                         "controlled": controlled})
            print(f"{name:<12}{integrator:<16}{cell(fixed):<36}{cell(controlled)}", flush=True)
    missed = [r for r in rows if r["controlled"]["outcome"] == "diverged"]
    rescued = [r for r in rows if r["fixed"]["outcome"] == "diverged" and r["controlled"]["outcome"] == "ok"]
    print(f"\nfixed default dt diverged: {sum(r['fixed']['outcome'] == 'diverged' for r in rows)} runs, "
          f"{len(rescued)} of them through with tol {args.tol:g}; error-controlled runs stopped with StepSizeError: "
          f"{len(missed)}" + "".join(f"\n  {r['scene']} {r['integrator']}: {r['controlled']['error']}" for r in missed))
    write_json(args.json, {"tol": args.tol, "budget_cpu_s": args.budget, "rows": rows})
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
