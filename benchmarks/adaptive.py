"""Error-controlled steps (``Simulation(tol=...)``): error against tol, and cost against fixed dt.

Per scene and integrator, over T = the study's default duration (a tenth of the
scene's; ``--duration`` to override) with ``horizon=T``:

1. tolerance proportionality: for each tol of ``--tols``, the adaptive run's error at
   T (the study's measure: RMS over the moving particles of |x - x_ref| over the
   scene's size) against a reference (RK4, ``analysis.reference.rk4``, from the
   scene's explicit dt made to divide T and halved until its change is below
   ``REFERENCE_RATIO`` x the smallest error measured, at most ``REFERENCE_HALVINGS``
   times; the check is recorded), error / tol, CPU time (``time.process_time``) and
   wall time (medians of ``--repeats`` runs after a warm-up that compiles the
   kernels), accepted steps, rejections, Newton and CG iterations;
2. efficiency: a fixed-dt ladder of the same integrator (``study.dt_ladder`` from the
   scene's dt for it, at most T / 10, halving, ``--rungs`` rungs at most, stopping
   once a rung's error is below every adaptive run's: after the first rung when no
   adaptive run finished), error and CPU time per rung;
   for each tol the CPU time a fixed-dt run of the adaptive run's error takes: the
   log-log interpolation between the two rungs whose errors bracket it (``fixed.how``
   "interpolated"), the coarsest rung if even that one is as accurate ("coarsest
   rung"); none if no rung is ("not reached": ``ratio_at_most`` bounds the ratio with the
   finest rung's time); also the cheapest rung at most that error ("cheapest_rung"); and
   the ratio adaptive / fixed.

A case (one adaptive tol, one rung) over ``--budget`` seconds is recorded as
"skipped: over budget": predicted from the previous tol's run (steps grow as
tol^(-1/order)) or rung (twice the steps) and not run, or stopped by a CPU-time alarm.
A case that raises (StepSizeError, DivergenceError, ...) is recorded with its message.

It imports the installed massspring unless the repository root comes first on the path
(``PYTHONPATH=.``, as the committed results were made).

    python benchmarks/adaptive.py                      # all scenes and integrators
    python benchmarks/adaptive.py --scenes spring chain --integrators bdf2 rk4 --tols 1e-2 1e-3
    python benchmarks/adaptive.py --json benchmarks/results/adaptive.json
"""

from __future__ import annotations

import argparse
import math
import signal
import statistics
import sys
import time
import traceback
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import output  # noqa: E402

import massspring as ms  # noqa: E402
from massspring.analysis import reference, study  # noqa: E402
from massspring.engine.adaptive import scene_size  # noqa: E402
from massspring.integrators import INTEGRATORS, SMALLEST_DT  # noqa: E402
from massspring.io.files import write_json  # noqa: E402

SCENES = {"spring": [], "chain": [], "cloth": ["resolution=16"], "stiffchain": [], "rope-drop": [],
          "drape": ["resolution=32"]}
TOLS = (1e-2, 1e-3, 1e-4, 1e-5)
RUNGS = 8
REFERENCE_RATIO = 1e-3  # the reference's change on halving / the smallest error measured must be below this
REFERENCE_HALVINGS = 3  # halvings tried beyond the first pair
ROUND_OFF = 1e-11  # errors below this are f64 round-off (RK4's fine rungs, free fall): not the check's scale
TARGETS = {"error_over_tol": (0.03, 30.0), "cpu_ratio": 1.5}


class OverBudget(Exception):
    pass


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", nargs="+", default=list(SCENES), help="scenes (default: "
                   f"{' '.join(SCENES)}; cloth at resolution 16, drape at 32)")
    p.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                   help="scene overrides applied to every scene after the defaults above")
    p.add_argument("--integrators", nargs="+", default=list(INTEGRATORS), choices=list(INTEGRATORS))
    p.add_argument("--tols", nargs="+", type=float, default=list(TOLS))
    p.add_argument("--duration", type=float, default=None, help="end time T (s; default: the study's, a tenth "
                   "of the scene's duration)")
    p.add_argument("--rungs", type=int, default=RUNGS, help=f"fixed-dt rungs at most (default {RUNGS})")
    p.add_argument("--repeats", type=int, default=1, help="timed runs per case, median (default 1)")
    p.add_argument("--budget", type=float, default=20.0, help="CPU seconds per case before it is skipped "
                   "(default 20)")
    output.add_json(p, "adaptive")
    return p.parse_args(argv)


def rms_error(x, ref, moving, size):
    d = x[moving] - ref[moving]
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1)))) / size


def message(error):
    """The recorded text of an exception; where it was raised too, for one that is no
    DivergenceError (a bug, not a verdict on the run)."""
    text = f"{type(error).__name__}: {error}"
    if not isinstance(error, ms.DivergenceError) and error.__traceback__ is not None:
        frame = traceback.extract_tb(error.__traceback__)[-1]
        text += f" (at {Path(frame.filename).name}:{frame.lineno})"
    return text


def _alarm(signum, frame):
    raise OverBudget()


def timed(run, budget):
    """(cpu s, wall s, result) of ``run()``, stopped by OverBudget past ``budget`` CPU seconds."""
    signal.signal(signal.SIGPROF, _alarm)
    signal.setitimer(signal.ITIMER_PROF, budget)
    cpu, wall = time.process_time(), time.perf_counter()
    try:
        result = run()
    finally:
        signal.setitimer(signal.ITIMER_PROF, 0)
    return time.process_time() - cpu, time.perf_counter() - wall, result


def close(sim):
    try:
        sim.close()
    except Exception:  # noqa: BLE001 - a run stopped mid-step may leave it half done
        pass


class Case:
    """One scene: its model, T, the reference and the runs."""

    def __init__(self, name, settings, duration):
        self.name = name
        self.scene = ms.load_scene(name).with_settings(settings) if settings else ms.load_scene(name)
        self.settings = settings
        self.model = self.scene.model()
        self.duration = study.default_duration(self.scene) if duration is None else duration
        self.size = scene_size(self.model)
        self.moving = self.model.free_mask()
        self.times = np.array([self.duration])
        dt = self.scene.default_dt(SMALLEST_DT)
        self.ref_dt = self.duration / math.ceil(self.duration / dt - 1e-9)
        self.coarse = reference.rk4(self.model, self.times, self.ref_dt).positions[-1]
        self.ref_dt /= 2
        self.ref = reference.rk4(self.model, self.times, self.ref_dt).positions[-1]

    def change(self):
        return rms_error(self.coarse, self.ref, self.moving, self.size)

    def refine(self, smallest):
        """Halve the reference while its change is not below REFERENCE_RATIO x ``smallest``:
        True if it changed (the errors must be measured again)."""
        changed = False
        for _ in range(REFERENCE_HALVINGS):
            if self.change() < REFERENCE_RATIO * smallest:
                break
            self.coarse = self.ref
            self.ref_dt /= 2
            self.ref = reference.rk4(self.model, self.times, self.ref_dt).positions[-1]
            changed = True
        return changed

    def error(self, x):
        return rms_error(x, self.ref, self.moving, self.size)

    def warm_up(self, integrator):
        dt = self.scene.default_dt(integrator)
        for options in ({}, {"tol": 1e-2, "horizon": self.duration}):
            sim = ms.Simulation(self.model, integrator=integrator, dt=dt, **options)
            try:
                if options:
                    sim.advance(3 * dt)
                else:
                    sim.step(2)
                    sim.step(1)
                sim.positions  # noqa: B018 - compiles the readback
            except Exception:  # noqa: BLE001 - a warm-up only compiles
                pass
            close(sim)

    def adaptive(self, integrator, tol, repeats, budget):
        first = min(self.scene.default_dt(integrator), self.duration / 10)
        row = {"tol": tol, "status": "ok"}
        samples = []
        for k in range(repeats):
            sim = ms.Simulation(self.model, integrator=integrator, dt=first, tol=tol, horizon=self.duration)
            try:
                cpu, wall, _ = timed(lambda: sim.advance(self.duration), budget)
            except OverBudget:
                row["status"] = (f"skipped: over budget (stopped after {budget:g} s CPU at t = {sim.time:.4g} s, "
                                 f"{sim.steps} steps)")
                close(sim)
                return row
            except Exception as error:  # noqa: BLE001 - recorded, the script goes on
                row["status"] = message(error)
                close(sim)
                return row
            samples.append((cpu, wall))
            if k == 0:
                stats = sim.control_stats()
                x = sim.positions
                row.update(x=x, accepted=stats["accepted"], rejected=stats["rejected"],
                           rejections=sum(stats["rejected"].values()), dt_min=stats["smallest_dt"],
                           dt_max=stats["largest_dt"], steps=sim.steps, newton_iterations=sum(sim.newton_iterations),
                           cg_iterations=sum(sim.cg_iterations))
            close(sim)
        row["cpu_s"] = statistics.median(s[0] for s in samples)
        row["wall_s"] = statistics.median(s[1] for s in samples)
        return row

    def fixed(self, integrator, dt, repeats, budget):
        n = int(round(self.duration / dt))
        row = {"dt": dt, "steps": n, "status": "ok"}
        samples = []
        for k in range(repeats):
            sim = ms.Simulation(self.model, integrator=integrator, dt=dt)
            try:
                cpu, wall, _ = timed(lambda: sim.step(n), budget)
            except OverBudget:
                row["status"] = f"skipped: over budget (stopped after {budget:g} s CPU, {sim.steps} of {n} steps)"
                close(sim)
                return row
            except Exception as error:  # noqa: BLE001
                row["status"] = message(error)
                close(sim)
                return row
            samples.append((cpu, wall))
            if k == 0:
                row.update(x=sim.positions, newton_iterations=sum(sim.newton_iterations),
                           cg_iterations=sum(sim.cg_iterations))
            close(sim)
        row["cpu_s"] = statistics.median(s[0] for s in samples)
        row["wall_s"] = statistics.median(s[1] for s in samples)
        return row


def equal_error_cost(target, rungs):
    """The CPU time (s) of a fixed-dt run of error ``target`` from the measured ``rungs``
    (coarsest first): {"cpu_s", "how", "cheapest_rung"} (see the module docstring)."""
    ok = [r for r in rungs if r.get("error") is not None and math.isfinite(r["error"]) and r["error"] < 1]
    reaching = [r for r in ok if r["error"] <= target]
    cheapest = min(reaching, key=lambda r: r["cpu_s"]) if reaching else None
    out = {"cheapest_rung": None if cheapest is None else {"dt": cheapest["dt"], "error": cheapest["error"],
                                                           "cpu_s": cheapest["cpu_s"]}}
    if not ok:
        return {**out, "cpu_s": None, "how": "no rung measured"}
    if ok[0]["error"] <= target and ok[0] is rungs[0]:
        return {**out, "cpu_s": ok[0]["cpu_s"], "how": "coarsest rung"}
    for a, b in zip(ok, ok[1:]):
        if a["error"] > target >= b["error"]:
            if b["error"] == target or a["error"] == b["error"]:
                return {**out, "cpu_s": b["cpu_s"], "how": "rung"}
            s = math.log(target / a["error"]) / math.log(b["error"] / a["error"])
            ca, cb = max(a["cpu_s"], 1e-6), max(b["cpu_s"], 1e-6)  # a clock tick: never log(0)
            cpu = math.exp(math.log(ca) + s * (math.log(cb) - math.log(ca)))
            return {**out, "cpu_s": cpu, "how": f"interpolated (log-log) between dt {a['dt']:.4g} and {b['dt']:.4g}"}
    if cheapest is not None:
        return {**out, "cpu_s": cheapest["cpu_s"], "how": "cheapest rung reaching it (errors not monotone)"}
    return {**out, "cpu_s": None, "how": "not reached", "finest_cpu_s": max(r["cpu_s"] for r in ok)}


def run_integrator(case, integrator, args):
    order = INTEGRATORS[integrator].traits.order
    case.warm_up(integrator)
    adaptive, last, over = [], None, False
    for tol in sorted(args.tols, reverse=True):
        if over:
            adaptive.append({"tol": tol, "status": "skipped: over budget (a looser tol was)"})
            continue
        if last is not None and "cpu_s" in last:
            predicted = last["cpu_s"] * (last["tol"] / tol) ** (1.0 / order)
            if predicted > args.budget:
                adaptive.append({"tol": tol, "status": f"skipped: over budget (predicted {predicted:.3g} s CPU from "
                                                      f"tol {last['tol']:g})"})
                over = True
                continue
        last = case.adaptive(integrator, tol, args.repeats, args.budget)
        adaptive.append(last)
        over = last["status"].startswith("skipped")
    errors = [case.error(r["x"]) for r in adaptive if "x" in r]
    smallest = min(errors) if errors else math.inf
    top = min(case.scene.default_dt(integrator), case.duration / 10)
    rungs, last = [], None
    for dt in study.dt_ladder(top, case.duration, args.rungs):
        if last is not None and "cpu_s" in last and 2 * last["cpu_s"] > args.budget:
            rungs.append({"dt": dt, "steps": int(round(case.duration / dt)),
                          "status": f"skipped: over budget (predicted {2 * last['cpu_s']:.3g} s CPU)"})
            break
        if last is not None and last["status"].startswith("skipped"):
            break
        last = case.fixed(integrator, dt, args.repeats, args.budget)
        rungs.append(last)
        if "x" in last and case.error(last["x"]) <= smallest:
            break
    return adaptive, rungs


def finish(case, adaptive, rungs):
    for r in adaptive + rungs:
        if "x" in r:
            r["error"] = case.error(r.pop("x"))
    for r in adaptive:
        if r.get("error") is not None:
            r["error_over_tol"] = r["error"] / r["tol"]
            r["fixed"] = equal_error_cost(r["error"], rungs)
            fixed = r["fixed"]["cpu_s"]
            r["cpu_ratio"] = None if not fixed else r["cpu_s"] / fixed
            if r["fixed"].get("finest_cpu_s"):
                r["ratio_at_most"] = r["cpu_s"] / r["fixed"]["finest_cpu_s"]


def monotone(adaptive):
    errors = [r["error"] for r in sorted(adaptive, key=lambda r: -r["tol"]) if r.get("error") is not None]
    return all(b < a for a, b in zip(errors, errors[1:])) if len(errors) > 1 else None


def verdicts(row, impact):
    lo, hi = TARGETS["error_over_tol"]
    out = {"error_in_range": lo <= row["error_over_tol"] <= hi}
    if row.get("cpu_ratio") is not None:
        out["cpu_ok"] = row["cpu_ratio"] < 1.0 if impact else row["cpu_ratio"] <= TARGETS["cpu_ratio"]
    return out


def main(argv=None):
    args = parse_args(argv)
    result = {"command": "python benchmarks/adaptive.py " + " ".join(sys.argv[1:] if argv is None else argv),
              "targets": {"error_over_tol": list(TARGETS["error_over_tol"]), "monotone": True,
                          "cpu_ratio_at_most": TARGETS["cpu_ratio"], "cpu_ratio_below_1_on": ["rope-drop", "drape"]},
              "scenes": []}
    for name in args.scenes:
        settings = SCENES.get(name, []) + list(args.set)
        case = Case(name, settings, args.duration)
        entry = {"scene": name, "settings": settings, "duration": case.duration, "size": case.size,
                 "particles": int(case.model.n_particles), "integrators": {}}
        raw = {}
        for integrator in args.integrators:
            raw[integrator] = run_integrator(case, integrator, args)
        measured = [case.error(r["x"]) for a, f in raw.values() for r in a + f if "x" in r]
        measured = [e for e in measured if e > ROUND_OFF]
        case.refine(min(measured) if measured else math.inf)
        smallest = min(measured) if measured else math.inf
        entry["reference"] = {"method": "rk4", "dt": case.ref_dt, "change": case.change(), "smallest_error": smallest,
                              "ratio": REFERENCE_RATIO, "passed": case.change() < REFERENCE_RATIO * smallest}
        print(f"\n{name} {' '.join(settings)}: T = {case.duration:g} s, {case.model.n_particles} particles; "
              f"reference RK4 dt {case.ref_dt:.3g}, change on halving {case.change():.2g} "
              f"({'PASS' if entry['reference']['passed'] else 'FAIL'})")
        print(f"  {'integrator':15s} {'tol':>7s} {'error':>9s} {'err/tol':>8s} {'CPU s':>8s} {'wall s':>8s} "
              f"{'steps':>7s} {'rej':>5s} {'Newton':>7s} {'CG':>8s} {'fixed s':>8s} {'ratio':>6s}  note")
        for integrator, (adaptive, rungs) in raw.items():
            finish(case, adaptive, rungs)
            for r in adaptive:
                if r.get("error") is not None:
                    r.update(verdicts(r, name in ("rope-drop", "drape")))
            entry["integrators"][integrator] = {"adaptive": adaptive, "fixed": rungs, "monotone": monotone(adaptive)}
            for r in adaptive:
                if r.get("error") is None:
                    print(f"  {integrator:15s} {r['tol']:7.0e}  {r['status']}")
                    continue
                fixed = r["fixed"]["cpu_s"]
                note = r["fixed"]["how"] if not r["fixed"]["how"].startswith("interp") else "interpolated"
                print(f"  {integrator:15s} {r['tol']:7.0e} {r['error']:9.2e} {r['error_over_tol']:8.3g} "
                      f"{r['cpu_s']:8.4f} {r['wall_s']:8.4f} {r['accepted']:7d} {r['rejections']:5d} "
                      f"{r['newton_iterations']:7d} {r['cg_iterations']:8d} "
                      f"{'' if fixed is None else format(fixed, '8.4f'):>8s} "
                      f"{'' if r['cpu_ratio'] is None else format(r['cpu_ratio'], '6.2f'):>6s}  {note}")
            for r in rungs:
                error = f"{r['error']:9.2e}" if r.get("error") is not None else ""
                cpu = f"{r['cpu_s']:.4g}" if "cpu_s" in r else ""
                print(f"  {'':15s} dt {r['dt']:.3g}: {r['steps']} steps, error {error} CPU {cpu}"
                      + ("" if r["status"] == "ok" else f"  {r['status']}"))
        result["scenes"].append(entry)
        write_json(args.json, result)  # as it goes: a stopped run keeps the scenes done
    write_json(args.json, result)
    print(f"\nwrote {args.json}")


if __name__ == "__main__":
    main()
