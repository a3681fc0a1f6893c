"""Which shipped scenes could take a default tolerance (``Simulation(tol=..., horizon=...)``)
that reproduces today's look at no more cost.

Per scene (default: every built-in scene but bigstep, whose fixed dt of 1 s is its point;
``--scenes`` to choose), with its default integrator at its default size, over T = the
scene's whole default duration (``--duration-fraction`` x it):

1. today's run: the fixed-dt run at the scene's default dt (made to divide T if it does
   not): its end error E0 (adaptive.py's measure: RMS over the moving particles of
   |x - x_ref| at T over the scene's size) and CPU time C0 (``time.process_time``, median
   of ``--repeats`` runs after adaptive.py's warm-up, which compiles the kernels);
2. error-controlled runs (``horizon`` = T, first dt = min(the scene's dt, T / 10), as
   adaptive.py) at each tol of ``--tols``, loosest first: end error, CPU time, accepted
   and rejected steps (by cause), Newton and CG iterations; the ladder stops after the first
   tol whose error is at most E0, or after a run stopped by adaptive.py's CPU-time alarm at
   ``--budget`` s; a run that raises is recorded with its message and the ladder goes on;
   each tol is timed once, the deciding one (below) ``--repeats`` times (median);
3. the verdict: the loosest tol whose error is at most E0 and its CPU time over C0;
   "yes" if that ratio is at most 1.0, "no" if above, "not reached" if no tol got to E0.
   A verdict is marked "close" when |error - E0| is within twice the reference's own
   change (below): the reference cannot tell the two apart.

The reference (``--reference``):
* ``rk4``: adaptive.py's (``analysis.reference.rk4`` from the scene's explicit dt made to
  divide T, halved; after the runs halved again while its change is not below
  adaptive.REFERENCE_RATIO x the smallest error measured, at most REFERENCE_HALVINGS times
  and while the next solve is predicted within ``--reference-budget`` CPU s);
* ``fine``: a fixed-dt run of the same integrator at the run's dt / 16; its check is the
  change from the dt / 8 run, which for these first-order integrators is about the fine
  run's own error; it passes when below FINE_RATIO x E0;
* ``auto`` (default): ``fine`` for the contact and self-collision scenes (CONTACT), whose RK4
  does not converge at any affordable dt, and for a scene whose RK4 pair (dt and dt / 2) is
  predicted (from a timed burst of RK4 steps) over ``--reference-budget``; ``rk4`` otherwise.
Each row records the reference used, its dt, change, check and CPU time.

It imports the installed massspring unless the repository root comes first on the path
(``PYTHONPATH=.``). RK4 references are cached as adaptive.py's are (``MASSSPRING_CACHE``).

    python benchmarks/scene_tols.py                                   # every scene but bigstep
    python benchmarks/scene_tols.py --scenes spring chain            # a quick check: a few minutes
    python benchmarks/scene_tols.py --scenes drape --reference fine --budget 10
    python benchmarks/scene_tols.py --json benchmarks/results/scene_tols.json
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import adaptive  # noqa: E402
import output  # noqa: E402

import massspring as ms  # noqa: E402
from massspring.analysis import reference, study  # noqa: E402
from massspring.engine.adaptive import scene_size  # noqa: E402
from massspring.integrators import REFERENCE, SMALLEST_DT  # noqa: E402
from massspring.io.files import write_json  # noqa: E402
from massspring.scene import builtin_scenes  # noqa: E402

LEFT_OUT = ("bigstep",)  # a fixed dt of 1 s is the scene's point
CONTACT = ("drape", "ledge", "rope-drop", "sheets", "tablecloth", "thrown")  # contact, self-collision: RK4 too costly or not converging
TOLS = (1e-1, 3e-2, 1e-2, 3e-3, 1e-3)
FINE = 16  # the fine reference's dt: the run's dt / FINE
FINE_RATIO = 0.1  # the fine reference's change (about its own error) / E0 must be below this
REFERENCE_BUDGET = 120.0  # CPU s for the RK4 reference's first pair; beyond it (predicted), the fine reference
BURST = 2000  # RK4 steps timed to predict a reference's cost
FIXED_BUDGET = 10  # today's run: stopped at this many times --budget only
FINE_REFERENCE_BUDGET = 1e5  # CPU s: the fine reference runs to its end


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    shipped = sorted(n for n in builtin_scenes() if n not in LEFT_OUT)
    p.add_argument("--scenes", nargs="+", default=shipped, help="scenes (default: every built-in one but "
                   f"{', '.join(LEFT_OUT)})")
    p.add_argument("--tols", nargs="+", type=float, default=list(TOLS), help="tolerances, tried loosest first "
                   f"(default {' '.join(f'{t:g}' for t in TOLS)})")
    p.add_argument("--duration-fraction", type=float, default=1.0, help="T = this x the scene's duration "
                   "(default 1: the whole of it)")
    p.add_argument("--repeats", type=int, default=3, help="timed runs of today's run and of the deciding tol, "
                   "median (default 3)")
    p.add_argument("--budget", type=float, default=20.0, help="CPU s per error-controlled run before it is stopped "
                   "and the ladder ends (default 20)")
    p.add_argument("--reference", choices=("auto", "rk4", "fine"), default="auto",
                   help="the reference (default auto: fine for the contact scenes and where RK4 is over "
                   "--reference-budget, else rk4)")
    p.add_argument("--reference-budget", type=float, default=REFERENCE_BUDGET,
                   help=f"CPU s the RK4 reference may take, predicted (default {REFERENCE_BUDGET:g})")
    output.add_json(p, "scene_tols")
    return p.parse_args(argv)


class SceneCase(adaptive.Case):
    """adaptive.Case over the whole duration (or a fraction of it), the reference made
    later (``rk4_reference`` or ``fine_reference``) rather than on construction."""

    def __init__(self, name, fraction):  # noqa: super().__init__ would compute the RK4 reference at once
        self.name = name
        self.scene = ms.load_scene(name)
        self.settings = []
        self.model = self.scene.model()
        self.duration = self.scene.duration * fraction
        self.size = scene_size(self.model)
        self.moving = self.model.free_mask()
        self.times = np.array([self.duration])
        self.integrator = self.scene.integrator
        self.scene_dt = self.scene.default_dt(self.integrator)
        self.dt = study.dt_ladder(self.scene_dt, self.duration, 1)[0]  # the scene's dt, made to divide T
        self.method = None
        self.ref = self.coarse = None
        self.ref_cpu = 0.0

    def rk4_solve_cpu(self):
        """Predicted CPU s of one RK4 solve at the scene's explicit dt over T (a timed burst)."""
        dt = self.scene.default_dt(SMALLEST_DT)
        sim = ms.Simulation(self.model, integrator=REFERENCE, dt=dt, precision="f64")
        try:
            sim.step(10)
            sim.positions  # noqa: B018 - compiles
            cpu = time.process_time()
            sim.step(BURST)
            sim.positions  # noqa: B018
            per_step = (time.process_time() - cpu) / BURST
        finally:
            adaptive.close(sim)
        self.burst = (per_step * math.ceil(self.duration / dt - 1e-9), dt)
        return self.burst[0]

    def _rk4(self, dt):
        cpu = time.process_time()
        x = reference.rk4(self.model, self.times, dt).positions[-1]
        self.ref_cpu += time.process_time() - cpu
        self.last_solve = time.process_time() - cpu
        return x

    def rk4_reference(self):
        self.method = "rk4"
        dt = self.scene.default_dt(SMALLEST_DT)
        self.ref_dt = self.duration / math.ceil(self.duration / dt - 1e-9)
        self.coarse = self._rk4(self.ref_dt)
        self.ref_dt /= 2
        self.ref = self._rk4(self.ref_dt)

    def refine(self, smallest, budget):
        """adaptive.Case.refine, each halving only while its solve is predicted (twice the
        last one's CPU time, or from the burst where that one came from the cache) within
        ``budget`` CPU s."""
        changed = False
        for _ in range(adaptive.REFERENCE_HALVINGS):
            if self.change() < adaptive.REFERENCE_RATIO * smallest:
                break
            per_solve, dt0 = self.burst
            predicted = max(2 * self.last_solve, per_solve * dt0 / (self.ref_dt / 2))
            if predicted > budget:
                self.refine_stopped = f"next halving predicted {predicted:.3g} s CPU, over {budget:g}"
                break
            self.coarse = self.ref
            self.ref_dt /= 2
            self.ref = self._rk4(self.ref_dt)
            changed = True
        return changed

    def fine_reference(self, budget):
        self.method = "fine"
        self.ref_dt = self.dt / FINE
        rows = []
        for dt in (self.dt / (FINE // 2), self.ref_dt):
            row = self.fixed(self.integrator, dt, 1, budget)
            if "x" not in row:
                raise RuntimeError(f"fine reference at dt {dt:.4g}: {row['status']}")
            self.ref_cpu += row["cpu_s"]
            rows.append(row["x"])
        self.coarse, self.ref = rows


def verdict(fixed, rows, change):
    """The loosest tol whose error is at most E0, and its CPU time over C0."""
    e0, c0 = fixed["error"], fixed["cpu_s"]
    for r in sorted(rows, key=lambda r: -r["tol"]):
        if r.get("error") is not None and r["error"] <= e0:
            ratio = r["cpu_s"] / c0 if c0 > 0 else math.inf
            out = {"tol": r["tol"], "error": r["error"], "cpu_s": r["cpu_s"], "cpu_ratio": ratio,
                   "answer": "yes" if ratio <= 1.0 else "no"}
            out["close"] = bool(abs(r["error"] - e0) <= 2 * change)
            return out
    reached = [r for r in rows if r.get("error") is not None]
    tightest = min(reached, key=lambda r: r["tol"]) if reached else None
    return {"tol": None, "answer": "not reached",
            "tightest_run": None if tightest is None else {"tol": tightest["tol"], "error": tightest["error"],
                                                           "cpu_s": tightest["cpu_s"]}}


def run_scene(name, args):
    case = SceneCase(name, args.duration_fraction)
    entry = {"scene": name, "integrator": case.integrator, "scene_dt": case.scene_dt, "dt": case.dt,
             "duration": case.duration, "size": case.size, "particles": int(case.model.n_particles),
             "springs": int(case.model.n_springs)}
    print(f"\n{name}: {case.integrator}, dt {case.dt:.4g} s, T = {case.duration:g} s, "
          f"{case.model.n_particles} particles", flush=True)
    method = args.reference
    if method == "auto":
        method = "fine" if name in CONTACT else "rk4"
        if method == "rk4":
            predicted = 3 * case.rk4_solve_cpu()  # a solve at the explicit dt, one at half of it
            entry["rk4_predicted_pair_cpu_s"] = predicted
            if predicted > args.reference_budget:
                method = "fine"
        why = ("contact or self-collision" if name in CONTACT else
               f"RK4 pair predicted {predicted:.3g} s CPU {'>' if method == 'fine' else '<='} "
               f"{args.reference_budget:g}")
    else:
        why = "--reference"
        if method == "rk4":
            case.rk4_solve_cpu()
    fixed_budget = FIXED_BUDGET * args.budget
    case.warm_up(case.integrator)
    if method == "rk4":
        case.rk4_reference()
    else:
        case.fine_reference(FINE_REFERENCE_BUDGET)
    print(f"  reference {method} ({why}): dt {case.ref_dt:.4g}, {case.ref_cpu:.1f} s CPU", flush=True)

    fixed = case.fixed(case.integrator, case.dt, args.repeats, fixed_budget)
    if "x" not in fixed:
        raise RuntimeError(f"today's fixed-dt run: {fixed['status']}")
    e0 = case.error(fixed["x"])
    print(f"  fixed dt {case.dt:.4g}: E0 {e0:.3e}, C0 {fixed['cpu_s']:.3f} s CPU ({fixed['steps']} steps)", flush=True)

    rows = []
    for tol in sorted(args.tols, reverse=True):
        row = case.adaptive(case.integrator, tol, 1, args.budget)
        rows.append(row)
        if "x" in row:
            error = case.error(row["x"])
            print(f"  tol {tol:7.0e}: error {error:.3e}, {row['cpu_s']:.3f} s CPU, {row['accepted']} accepted, "
                  f"{row['rejections']} rejected", flush=True)
            if error <= e0:
                samples = [row["cpu_s"]]
                for _ in range(args.repeats - 1):
                    again = case.adaptive(case.integrator, tol, 1, args.budget)
                    if "cpu_s" in again:
                        samples.append(again["cpu_s"])
                row["cpu_samples"] = samples
                row["cpu_s"] = statistics.median(samples)
                row["wall_s"] = None  # the ladder's run's only; cpu_s is the median of cpu_samples
                break
        else:
            print(f"  tol {tol:7.0e}: {row['status']}", flush=True)
            if row["status"].startswith("skipped"):
                break

    measured = [case.error(r["x"]) for r in rows + [fixed] if "x" in r]
    measured = [e for e in measured if e > adaptive.ROUND_OFF]
    smallest = min(measured) if measured else math.inf
    if method == "rk4":
        case.refine_stopped = None
        case.refine(smallest, args.reference_budget)
        change = case.change()
        check = {"ratio": adaptive.REFERENCE_RATIO, "against": "smallest error measured", "smallest_error": smallest,
                 "passed": bool(change < adaptive.REFERENCE_RATIO * smallest)}
        if case.refine_stopped:
            check["halving_stopped"] = case.refine_stopped
    else:
        change = case.change()
        check = {"ratio": FINE_RATIO, "against": "E0", "passed": bool(change < FINE_RATIO * e0)}
    entry["reference"] = {"method": method, "why": why, "dt": case.ref_dt, "change": change,
                          "change_from": f"dt {2 * case.ref_dt:.4g}", "cpu_s": case.ref_cpu, **check}
    for r in rows + [fixed]:
        if "x" in r:
            r["error"] = case.error(r.pop("x"))
    for r in rows:
        if r.get("error") is not None:
            r["error_over_tol"] = r["error"] / r["tol"]
            r["cpu_over_c0"] = r["cpu_s"] / fixed["cpu_s"] if fixed["cpu_s"] > 0 else None
    entry["fixed"] = fixed
    entry["adaptive"] = rows
    entry["verdict"] = verdict(fixed, rows, change)
    v = entry["verdict"]
    print(f"  reference check: change {change:.2g} ({'PASS' if check['passed'] else 'FAIL'}); verdict: "
          + (f"tol {v['tol']:g}, CPU {v['cpu_ratio']:.2f} x C0: {v['answer']}{' (close)' if v['close'] else ''}"
             if v["tol"] is not None else v["answer"]), flush=True)
    return entry


def cell(row):
    if row is None:
        return "-"
    if row.get("error") is None:
        return "raised" if not row["status"].startswith("skipped") else "over budget"
    return f"{row['error']:.2e}/{row['cpu_s']:.2f}s"


def summary(result, tols):
    tols = sorted(tols, reverse=True)
    head = (f"{'scene':11s} {'integrator':14s} {'dt':>7s} {'ref':4s} {'E0':>8s} {'C0 s':>6s} "
            + " ".join(f"{f'tol {t:g}':>16s}" for t in tols) + "  verdict")
    print("\n" + head + "\n" + "-" * len(head))
    for e in result["scenes"]:
        if "error" in e:
            print(f"{e['scene']:11s} raised: {e['error']}")
            continue
        by_tol = {r["tol"]: r for r in e["adaptive"]}
        v = e["verdict"]
        text = (f"tol {v['tol']:g}: {v['cpu_ratio']:.2f} x C0, {v['answer']}{' (close)' if v['close'] else ''}"
                if v["tol"] is not None else v["answer"])
        print(f"{e['scene']:11s} {e['integrator']:14s} {e['dt']:7.4g} {e['reference']['method']:4s} "
              f"{e['fixed']['error']:8.2e} {e['fixed']['cpu_s']:6.2f} "
              + " ".join(f"{cell(by_tol.get(t)):>16s}" for t in tols) + f"  {text}")
    print("(each tol: end error / CPU s; the deciding tol's CPU the median of --repeats runs)")


def main(argv=None):
    args = parse_args(argv)
    result = {"command": "python benchmarks/scene_tols.py " + " ".join(sys.argv[1:] if argv is None else argv),
              "measures": "per scene, default integrator and size, over duration_fraction x its duration: today's "
                          "fixed-dt run (E0, C0) and error-controlled runs (horizon = T) at each tol, loosest first, "
                          "until one's error is at most E0; verdict: that tol's CPU / C0, yes if at most 1",
              "tols": sorted(args.tols, reverse=True), "duration_fraction": args.duration_fraction,
              "repeats": args.repeats, "budget_cpu_s": args.budget, "reference": args.reference,
              "reference_budget_cpu_s": args.reference_budget, "fine_dt_divisor": FINE, "scenes": []}
    for name in args.scenes:
        wall = time.perf_counter()
        try:
            entry = run_scene(name, args)
        except Exception as error:  # noqa: BLE001 - recorded, the script goes on
            entry = {"scene": name, "error": adaptive.message(error)}
            print(f"\n{name}: raised {entry['error']}", flush=True)
        entry["wall_s"] = time.perf_counter() - wall
        result["scenes"].append(entry)
        write_json(args.json, result)  # as it goes: a stopped run keeps the scenes done
    summary(result, args.tols)
    write_json(args.json, result)
    print(f"\nwrote {args.json}")


if __name__ == "__main__":
    main()
