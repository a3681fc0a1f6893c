"""``massspring run``: a scene from start (or a restart) to its end, its summary and its outputs."""

from __future__ import annotations

import math
import signal
import sys
import time

import numpy as np

from massspring.support import progress
from massspring.passes import strain_limit
from massspring.support.defaults import MAX_STEPS
from massspring.support.text import format_seconds
from massspring.cli.common import (
    EXIT_DIVERGED, EXIT_INTERRUPTED, EXIT_OK, EXIT_OUTPUT, Terminated, UsageError, main_thread, make_simulation)
from massspring.cli.pictures import finish_export, finish_pictures, plan_export, plan_frames, plan_pictures


def adaptive_hint(error) -> str:
    """What to try after an error-controlled run stopped below min_dt (``StepSizeError``):
    where its steps diverged however short, a bound on the steps before it (a long step
    of the linearised implicit Euler can end in a state no shorter step recovers from:
    docs/solvers.md, "Error-controlled steps"), else a smaller --min-dt or a looser --tol."""
    tips = "a smaller --min-dt, a looser --tol or another --integrator"
    if getattr(error, "cause", "") == "the state diverged":
        return f"give a --max-dt below the largest step above, {tips}"
    return f"give {tips}"


LONG_RUN_STEPS = 10**7  # an error-controlled run whose step bound means at least this many steps is named first


def bound_note(args, sim, seconds) -> str | None:
    """The warning before an error-controlled run of ``seconds`` s whose largest step
    (``max_dt``) means at least ``LONG_RUN_STEPS`` steps, naming the bound and where it
    comes from (an explicit integrator on an undamped stiff model: half a stability
    limit of 1e-10 s), else None."""
    from massspring.engine.spectrum import predict
    from massspring.integrators import INTEGRATORS

    bound, cls = sim.settings.max_dt, INTEGRATORS[sim.integrator]
    if sim.tol is None or not seconds / bound >= LONG_RUN_STEPS:
        return None
    if args.max_dt is not None:
        why = "--max-dt"
    elif cls.traits.stability_limited:
        suggested = cls.suggest_dt(predict(sim.model))
        why = ("half its stability limit predicted here" if suggested >= bound else
               f"--min-dt, above the {suggested:.3g} s of half its stability limit predicted here")
    else:
        why = "--min-dt"
    return (f"{sim.integrator}'s steps are held at most {bound:.3g} s ({why}): at least {seconds / bound:.3g} steps "
            f"for the {seconds:g} s; an implicit --integrator is not held so")


def run_steps(args, scene, sim, start_steps=0):
    """The number of steps of ``run``, checked: --steps, or --duration / dt; neither:
    what is left of the scene's duration after ``start_steps`` (a restart's)."""
    if args.steps is not None:
        if not 0 <= args.steps <= MAX_STEPS:
            raise UsageError(f"--steps: must be within 0..{MAX_STEPS}, got {args.steps}")
        return args.steps
    duration = scene.duration if args.duration is None else args.duration
    if not (math.isfinite(duration) and duration > 0):
        raise UsageError(f"--duration: must be a finite number > 0, got {duration:g}")
    steps = duration / sim.dt
    if not steps <= MAX_STEPS:  # also an infinite quotient
        raise UsageError(f"--duration: {duration:g} s at dt = {format_seconds(sim.dt)} is {steps:.3g} steps, "
                         f"more than {MAX_STEPS:.3g}")
    if args.duration is None:
        return max(0, max(1, round(steps)) - start_steps)
    if steps < 1:
        raise UsageError(f"--duration: {duration:g} s is shorter than one step (dt = {format_seconds(sim.dt)}); "
                         "give a longer --duration, a smaller --dt or --steps")
    return round(steps)


SLOTS = 10**9  # an error-controlled run's frame plan: frames at multiples of duration / SLOTS
PROGRESS_UNITS = 1000


def run_seconds(args, scene, sim):
    """The simulated seconds of an error-controlled ``run`` (--tol): --duration, else what is
    left of the scene's duration after a restart; --steps is refused (UsageError)."""
    if args.steps is not None:
        raise UsageError("--steps: an error-controlled run (--tol) picks its own steps; give --duration (s)")
    if args.duration is not None:
        if not (math.isfinite(args.duration) and args.duration > 0):
            raise UsageError(f"--duration: must be a finite number > 0, got {args.duration:g}")
        return args.duration
    left = scene.duration - sim.time
    if not left > 0:
        raise UsageError(f"--restart: the saved state is at t = {sim.time:g} s, at or past the scene's duration "
                         f"{scene.duration:g} s; give --duration")
    return left


def cmd_run(args):
    from massspring.support.errors import DivergenceError
    from massspring.io.files import check_writable
    from massspring.engine.simulation import run

    scene, sim = make_simulation(args)
    start_steps = restart(args, scene, sim)
    controlled = sim.tol is not None
    if controlled:  # measured in time: "steps" are slots of the frame plan (SLOTS over the duration)
        seconds = run_seconds(args, scene, sim)
        steps = SLOTS
    else:
        steps = run_steps(args, scene, sim, start_steps)
    if args.out is not None:
        check_writable(args.out, "--out", (".npz",))
    frames = plan_frames(args, sim, steps, seconds if controlled else None)
    pictures = plan_pictures(args, scene, sim, steps, frames)
    export = plan_export(args, scene, sim, steps, frames)  # last: it creates the directory
    callbacks = [c for c in (pictures.recording.record if pictures else None, export) if c is not None]

    def on_frame(state):
        for callback in callbacks:
            callback(state)

    note = bound_note(args, sim, seconds) if controlled else None
    if note is not None and not args.quiet:
        print(f"massspring: run {scene.name}: {note}", file=sys.stderr)
    energy0, start_time = sim.energy(), sim.time
    end_time = start_time + (seconds if controlled else 0.0)
    with RunSignals() as signals:
        start = time.perf_counter()
        stopped, diverged = None, None
        try:
            if controlled:
                label = f"run {scene.name} ({sim.integrator}, tol {sim.tol:g})"
                with progress.steps(label, PROGRESS_UNITS, seconds / PROGRESS_UNITS, show=not args.quiet,
                                    unit="1/1000 of the run") as on_progress:
                    times = None if frames is None else [k * seconds / SLOTS for k in frames]
                    run(sim, duration=seconds, frames=times if callbacks else (),
                        on_frame=on_frame if callbacks else None,
                        progress=None if on_progress is None else
                        (lambda done, total: on_progress(round(PROGRESS_UNITS * done / total), PROGRESS_UNITS)))
            else:
                label = f"run {scene.name} ({sim.integrator}, dt {format_seconds(sim.dt)})"
                with progress.steps(label, steps, sim.dt, show=not args.quiet and steps > 1) as on_progress:
                    run(sim, steps, frames=frames if callbacks else (), on_frame=on_frame if callbacks else None,
                        progress=on_progress)
        except KeyboardInterrupt as exc:  # Ctrl-C or SIGTERM: the simulation holds the state reached
            stopped = exc
        except DivergenceError as exc:  # the simulation holds the last good state
            diverged = exc
        signals.record_only()  # from here a signal stops the rendering only, never a write
        wall = time.perf_counter() - start
        if pictures is not None and (diverged or stopped):
            pictures.recording.record_last(sim)  # the picture ends on the last good state
        reached = None  # where a run that ended early stopped
        if diverged or stopped:
            reached = (f"t = {sim.time:.6g} s of {end_time:g} s" if controlled
                       else f"step {sim.steps} of {start_steps + steps}")
        failed = write_outputs(args, scene, sim, reached, pictures, signals.arrived)
        if export is not None:
            failed += finish_export(export, sim, reached, diverged, stopped)
        print_summary(scene, sim, wall, energy0, args.out if args.out and "--out" not in failed else None,
                      start_steps, start_time)
        done = sim.steps - start_steps
        if diverged is not None:
            hint = (adaptive_hint(diverged) if sim.tol is not None else divergence_hint(sim, diverged))
            print(f"massspring: {diverged}; {hint}", file=sys.stderr)
            return EXIT_DIVERGED
        if stopped is not None:
            what = "terminated" if isinstance(stopped, Terminated) else "interrupted"
            where = f"{done} steps, at {reached}" if controlled else f"{done} of {steps} steps"
            print(f"massspring: {what} after {where}; the state reached so far "
                  f"{'was written' if args.out and '--out' not in failed else 'is above'}", file=sys.stderr)
            return 128 + stopped.signum if isinstance(stopped, Terminated) else EXIT_INTERRUPTED
        if signals.signum is not None:  # the run had ended; a signal cut the pictures short
            print(f"massspring: {'terminated' if signals.signum == signal.SIGTERM else 'interrupted'} while writing "
                  "the outputs; what was written is listed above", file=sys.stderr)
            return 128 + signals.signum
        return EXIT_OUTPUT if failed else EXIT_OK


def restart(args, scene, sim):
    """With --restart, put the saved state into ``sim`` after checking that it belongs to
    this model and (for fixed steps) dt; an error-controlled ``sim`` continues from the
    saved time, with the saved run's controller if it was one of the same integrator.
    Returns the steps it had taken (0 without --restart)."""
    from massspring.io.state import read_state

    if args.restart is None:
        return 0
    try:
        state = read_state(args.restart, sim.model, f"the model of scene {scene.name!r}")
    except ValueError as exc:
        raise UsageError(f"--restart: {exc}") from None
    model, path = sim.model, args.restart
    if state.fingerprint != model.fingerprint():
        raise UsageError(f"--restart: {path} was saved from another model (scene {state.scene!r}, fingerprint "
                         f"{state.fingerprint[:12]}) than this run's (scene {scene.name!r}, {model.fingerprint()[:12]}):"
                         f" a different scene file or --set")
    clocked = sim.tol is not None  # an error-controlled run continues from the saved time
    if not clocked and not math.isclose(state.time, state.steps * state.dt, rel_tol=1e-12, abs_tol=1e-300):
        raise UsageError(f"--restart: {path} is at t = {state.time:.6g} s after {state.steps} steps, not "
                         f"{state.steps} x dt = {state.steps * state.dt:.6g} s: an error-controlled run's state, which "
                         f"fixed steps cannot continue; give --tol (and --duration, not --steps)")
    if not clocked and state.dt != sim.dt:
        raise UsageError(f"--restart: {path} was computed with dt = {state.dt!r} s and this run's dt is "
                         f"{sim.dt!r} s; time is counted in steps of dt, so pass --dt {state.dt!r}")
    try:
        same = state.integrator == sim.integrator
        sim.set_state(state.positions, state.velocities, state.steps, state.carried if same else None,
                      time=state.time if clocked else None, control=state.control if same and clocked else None)
    except ValueError as exc:
        raise UsageError(f"--restart: {path}: {exc}") from None
    return state.steps


class RunSignals:
    """SIGINT and SIGTERM from the start of a run to the end of its outputs. The first
    one during the steps stops them (KeyboardInterrupt; ``Terminated`` for SIGTERM);
    after that one, and once ``record_only()`` is called as the steps end, a signal is
    only recorded (``signum``: the first recorded), so a second Ctrl-C can cut no file
    write short: the rendering asks ``arrived()`` between frames and stops."""

    def __init__(self):
        self.signum, self.previous, self.raising = None, {}, True

    def _handle(self, signum, frame):
        if self.raising:
            self.raising = False
            raise Terminated(signum) if signum == signal.SIGTERM else KeyboardInterrupt()
        self.signum = self.signum or signum

    def record_only(self):
        self.raising = False

    def arrived(self):
        return self.signum is not None

    def __enter__(self):
        if main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self.previous[sig] = signal.signal(sig, self._handle)
        return self

    def __exit__(self, *exc):
        for sig, handler in self.previous.items():
            signal.signal(sig, handler)


def write_outputs(args, scene, sim, reached, pictures, stop=None):
    """Write --out, then the pictures, each on its own: one failing does not stop the
    others (``reached``: where a run that ended early stopped, as text, None if it ran
    to its end; ``stop()``: true when the rendering should end early). Returns the
    options whose output failed (each reported on stderr)."""
    from massspring.io.state import write_state

    failed = []
    if args.out:
        try:
            write_state(sim, args.out, scene.name)
        except OSError as exc:
            print(f"massspring: --out: could not write {args.out!r}: {exc.strerror or exc}", file=sys.stderr)
            failed.append("--out")
    if pictures is not None:
        failed += finish_pictures(pictures, scene, sim, reached, stop)
    return failed


def divergence_hint(sim, exc):
    """What to try after a divergence, from the integrator and the stability estimate."""
    from massspring.analysis.stability import predict
    from massspring.integrators import DEFAULT, INTEGRATORS

    if INTEGRATORS[sim.integrator].traits.linear_solver:
        tips = ["a smaller --dt"]
        if not sim.definiteness_fix:
            tips.insert(0, "dropping --no-definiteness-fix")
        return "try " + " or ".join(tips)
    try:
        prediction = predict(sim.model, sim.model.positions)
    except (ValueError, ArithmeticError):
        return f"try a smaller --dt or --integrator {DEFAULT}"

    suggested = INTEGRATORS[sim.integrator].suggest_dt(prediction)
    if suggested >= sim.dt:  # the estimate at the initial state did not hold for this run
        return (f"try --dt {sim.dt / 4:.3g} (a quarter of this run's; the stability estimate for {sim.integrator} "
                f"at the initial state, {suggested:.3g} s, did not hold as the state changed) or --integrator "
                f"{DEFAULT} (no stability limit)")
    if INTEGRATORS[sim.integrator].traits.grows_undamped and not prediction.explicit_stable_dt > 0:
        stable = [name for name, cls in INTEGRATORS.items() if cls.traits.limit_reference or cls.traits.linear_solver]
        stable = ", ".join(stable[:-1]) + " or " + stable[-1]
        return (f"{sim.integrator} grows at every dt on this scene's undamped stiffest mode; --dt {suggested:.3g} "
                f"keeps that growth under 2x per simulated second, or try --integrator {stable}")
    return (f"try --dt {suggested:.3g} (the stability estimate for {sim.integrator} at the initial state) "
            f"or --integrator {DEFAULT} (no stability limit)")


def print_summary(scene, sim, wall, energy0, out, start_steps=0, start_time=0.0):
    info = sim.info()
    energy1 = sim.energy()
    done = sim.steps - start_steps
    rate = done / wall if wall > 0 else float("inf")
    print(f"scene       {scene.name} ({info['particles']} particles, {info['springs']} springs)")
    control = sim.control_stats()
    if control is None:
        print(f"integrator  {sim.integrator}, dt = {format_seconds(sim.dt)}, {sim.precision}")
    else:
        rejected = ", ".join(f"{count} {cause}" for cause, count in control["rejected"].items() if count) or "none"
        span = ("no step" if control["smallest_dt"] is None else
                f"dt {format_seconds(control['smallest_dt'])} to {format_seconds(control['largest_dt'])}")
        batched = f"; {control['batched']} in calm batches" if control["batched"] else ""
        print(f"integrator  {sim.integrator}, tol {sim.tol:g} ({span}; rejected: {rejected}{batched}), {sim.precision}")
    if start_steps:
        print(f"steps       {done} from the restart at step {start_steps} to step {sim.steps} (t = "
              f"{start_time:g} to {sim.time:g} s) in {wall:.2f} s wall, {rate:.3g} steps/s")
    else:
        print(f"steps       {sim.steps} ({sim.time:g} s simulated) in {wall:.2f} s wall, {rate:.3g} steps/s")
    if sim.newton_iterations:
        newton = np.array(sim.newton_iterations)
        tol = "from --tol" if control is not None else f"tol {sim.newton_tol:g}"
        print(f"Newton      {newton.mean():.2f} iterations/step mean, {newton.max()} max, {sim.line_search_cuts} "
              f"line-search cut(s), {sim.cg_failures} step(s) not converged ({tol})")
        if sim.cg_failures:
            print(f"note        Newton stopped at --newton-max-iter {sim.newton_max_iter} before --newton-tol "
                  f"{sim.newton_tol:g} on {sim.cg_failures} of {len(newton)} steps: raise --newton-max-iter, "
                  f"or take a smaller --dt (a step closer to its start converges in fewer iterations)")
    if sim.cg_iterations:
        its = np.array(sim.cg_iterations)
        failed = "" if sim.newton_iterations else f", {sim.cg_failures} step(s) not converged"
        tol = "from --tol" if control is not None else f"tol {sim.cg_tol:g}"
        print(f"CG          {its.mean():.1f} iterations/step mean, {its.max()} max{failed} ({tol}, "
              f"{sim.preconditioner})")
        if sim.cg_failures and sim.precision == "f32":
            print("note        f32 CG stalls where round-off stops the residual, 1e-5 to 1e-4 relative "
                  "on a cloth at rest: use --cg-tol 1e-3 or --precision f64")
        if sim.cg_failures and not sim.definiteness_fix:
            print("note        CG stops when A is indefinite, as compressed springs make it without the "
                  "definiteness fix: drop --no-definiteness-fix")
    limit = sim.strain_limit_stats
    if limit is not None:
        unmet = f", {limit['unmet']} step(s) left over it after {strain_limit.ITERATIONS}" if limit["unmet"] else ""
        if limit["undone"]:
            unmet += (f" ({limit['undone']} of them undone: the pass made the worst spring worse, its pins or "
                      "colliders holding it past the limit)")
        print(f"strain      limit {sim.model.strain_limit:g}: {limit['steps']} step(s) shortened springs, "
              f"{limit['most']} iterations at most{unmet}")
    print("energy      " + format_energy(energy0, energy1))
    print(f"compiled    terms: {', '.join(info['terms'])}; arrays: {', '.join(info['arrays'])} "
          f"({info['loops']} loops)")
    if out:
        print(f"wrote       {out}")


def format_energy(start, end):
    """Energies (J, ``Model.energy``: kinetic, spring, each uniform force's potential, total)
    at a precision that matches what they mean: each to 4 significant digits, and 0
    where it is round-off (below 1e-12 of the largest energy involved)."""
    scale = max(abs(v) for e in (start, end) for v in e.values()) or 1.0

    def fmt(value):
        return "0" if abs(value) <= 1e-12 * scale else f"{value:.4g}"

    parts = ", ".join(f"{name} {fmt(value)}" for name, value in end.items() if name != "total")
    return f"start {fmt(start['total'])} J, end {fmt(end['total'])} J ({parts})"
