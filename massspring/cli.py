"""The massspring command line: run built-in or user scenes, list them, describe them.

It parses, calls and prints: the physics is in ``Simulation`` and the run loop in
``simulation.run``. Exit codes: 0 success; 2 bad usage or bad input (one line on
stderr, no traceback), decided before the first step; 3 the simulation diverged
(the last good state is still summarised and written); 1 an output could not be
written after the run; 130 interrupted by Ctrl-C, 143 by SIGTERM (the state reached
so far is still summarised and written).
"""

from __future__ import annotations

import argparse
import math
import signal
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from massspring import progress, validate
from massspring.defaults import MAX_STEPS, PRECISIONS
from massspring.text import clipped, format_seconds

EXIT_OK, EXIT_OUTPUT, EXIT_USAGE, EXIT_DIVERGED, EXIT_INTERRUPTED = 0, 1, 2, 3, 130


class UsageError(ValueError):
    """Bad command-line input; reported in one line with exit code 2."""


class Terminated(KeyboardInterrupt):
    """SIGTERM (timeout, container stop, batch scheduler): handled like Ctrl-C."""

    def __init__(self, signum):
        super().__init__(signum)
        self.signum = signum


class Parser(argparse.ArgumentParser):
    """argparse's parser, its error messages ``clipped`` (a 100 KB argument is not echoed whole)."""

    def error(self, message):
        super().error(clipped(message))


def build_parser():
    from massspring import __version__
    from massspring.integrators import INTEGRATORS

    parser = Parser(prog="massspring", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"massspring {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=Parser)
    verbs = {}

    run = verbs["run"] = sub.add_parser("run", help="run a scene and print a summary")
    add_scene_arguments(run, INTEGRATORS)
    length = run.add_mutually_exclusive_group()
    length.add_argument("--steps", type=int, help="number of steps (default: the scene's duration / dt)")
    length.add_argument("--duration", type=float, help="simulated seconds (default: the scene's)")
    run.add_argument("--out", help="write the final state to this .npz file")
    run.add_argument("--restart", metavar="FILE", help="continue from a state written by --out (or an npz "
                     "frame of --export) of the same scene and dt; --steps/--duration then count the steps to "
                     "add, and without them the run finishes the scene's duration")
    run.add_argument("--quiet", action="store_true",
                     help="no progress (a bar on a terminal, else a line every 5 s of a long run)")
    add_export_arguments(run)
    add_frame_arguments(run)

    scenes = verbs["scenes"] = sub.add_parser("scenes", help="list the built-in scenes")
    scenes.add_argument("--markdown", action="store_true", help="as a Markdown table (the README's)")

    info = verbs["info"] = sub.add_parser("info", help="show a scene's size, defaults, and what a run compiles")
    add_scene_arguments(info, INTEGRATORS)

    stab = verbs["stability"] = sub.add_parser(
        "stability", help="predict each integrator's dt limit from the spectrum, then run a ladder of dt around it")
    add_stability_arguments(stab, INTEGRATORS)

    study = verbs["study"] = sub.add_parser(
        "study", help="work-precision study: error against run time per integrator and dt")
    add_study_arguments(study)

    sweep = verbs["sweep"] = sub.add_parser(
        "sweep", help="run a scene once per combination of varied parameters, here or on a Dask cluster")
    add_sweep_arguments(sweep, INTEGRATORS)
    return parser, verbs


def add_scene_arguments(p, integrators):
    from massspring.device import ARCHS
    from massspring.integrators.newton import NEWTON_MAX_ITER, NEWTON_TOL
    from massspring.solvers import CHOICES, MULTIGRID_FROM

    p.add_argument("scene", help="a built-in scene name (see `massspring scenes`) or a TOML file")
    p.add_argument("--integrator", choices=tuple(integrators), help="time integrator (default: the scene's)")
    p.add_argument("--dt", type=float, help="time step in s (default: the scene's for the integrator)")
    p.add_argument("--precision", choices=PRECISIONS, default=PRECISIONS[0])
    p.add_argument("--arch", default="cpu", help=f"Taichi arch: {', '.join(ARCHS)} (default cpu); another "
                   "than the CPU is tried before the run and refused if this machine lacks it")
    p.add_argument("--cg-tol", type=float, help="implicit integrators: CG tolerance relative to the first "
                   "residual of each solve (backward-euler, bdf2: the tightest) (default: the scene's "
                   "[solver], else 1e-6)")
    p.add_argument("--cg-max-iter", type=int, help="implicit integrators: CG iteration limit per solve "
                   "(default: the scene's [solver], else 3 x free particles, at least 100)")
    p.add_argument("--newton-tol", type=float, help="backward-euler, bdf2: Newton stops when a full Newton "
                   "step changes the velocities by at most this fraction of the step's velocity change "
                   f"(default: the scene's [solver], else {NEWTON_TOL:g})")
    p.add_argument("--newton-max-iter", type=int, help="backward-euler, bdf2: Newton iterations per step at "
                   f"most (default: the scene's [solver], else {NEWTON_MAX_ITER})")
    p.add_argument("--preconditioner", choices=CHOICES,
                   help="implicit integrators: the CG's preconditioner (default: the scene's [solver], else "
                   f"auto: multigrid from {MULTIGRID_FROM:,} free particles, block-jacobi below)")
    p.add_argument("--no-definiteness-fix", action="store_true",
                   help="implicit integrators: use the stiffness of Eq. 13 as written (indefinite when springs "
                   "are compressed)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a scene model parameter, e.g. --set resolution=64, "
                   "--set gravity=[0,0,-1.62] or --set drag=0.005 (TOML values; repeatable)")


def make_simulation(args):
    """Scene + options -> (scene, Simulation); raises ValueError on bad input before any kernel runs."""
    from massspring.device import ensure_taichi
    from massspring.integrators import INTEGRATORS
    from massspring.scene import load_scene

    scene = load_scene(args.scene).with_settings(args.set)
    options = solver_options(args)
    try:
        if args.dt is not None:
            validate.positive_float("--dt", args.dt)
        ensure_taichi(args.arch, "--arch")
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    integrator = args.integrator or scene.integrator
    for flags, needs, lacks in ((SOLVER_OPTIONS, "linear_solver", "solves no linear system"),
                                (NEWTON_OPTIONS, "newton", "takes no Newton iterations")):
        given = [option for option, key in flags.items() if key in options]
        if given and not getattr(INTEGRATORS[integrator], needs):
            raise UsageError(f"{'/'.join(given)}: {integrator} {lacks}; "
                             f"{'these options are' if len(given) > 1 else 'this option is'} for "
                             + ", ".join(k for k, cls in INTEGRATORS.items() if getattr(cls, needs)))
    with progress.phase(f"{args.command} {scene.name}: building the model and the simulation",
                        show=not getattr(args, "quiet", False)):
        sim = scene.simulation(integrator=args.integrator, dt=args.dt, precision=args.precision, arch=args.arch,
                               **options)
    return scene, sim


# The implicit solver's command-line options -> Simulation arguments.
SOLVER_OPTIONS = {"--cg-tol": "cg_tol", "--cg-max-iter": "cg_max_iter", "--preconditioner": "preconditioner",
                  "--no-definiteness-fix": "definiteness_fix"}
NEWTON_OPTIONS = {"--newton-tol": "newton_tol", "--newton-max-iter": "newton_max_iter"}


def solver_options(args):
    """The implicit solver's options given on the command line, checked (UsageError
    naming the option); the scene's [solver] table (``Scene.simulation``) supplies the
    others."""
    options = {}
    try:
        if args.cg_tol is not None:
            options["cg_tol"] = validate.fraction("--cg-tol", args.cg_tol)
        if args.cg_max_iter is not None:
            options["cg_max_iter"] = validate.count("--cg-max-iter", args.cg_max_iter)
        if args.newton_tol is not None:
            options["newton_tol"] = validate.fraction("--newton-tol", args.newton_tol)
        if args.newton_max_iter is not None:
            options["newton_max_iter"] = validate.count("--newton-max-iter", args.newton_max_iter)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    if args.preconditioner is not None:
        options["preconditioner"] = args.preconditioner
    if getattr(args, "no_definiteness_fix", False):
        options["definiteness_fix"] = False
    return options


def cmd_scenes(args):
    from massspring.scene import builtin_scenes, load_scene

    names = sorted(builtin_scenes())
    if not args.markdown:
        for name in names:
            print(f"{name:12s} {load_scene(name).description}")
        return EXIT_OK
    print("| scene | what | particles | springs | integrator, dt |\n|---|---|---|---|---|")
    for name in names:
        scene = load_scene(name)
        model = scene.model()
        print(f"| {name} | {scene.description} | {model.n_particles:,} | {model.n_springs:,} | "
              f"{scene.integrator}, {format_seconds(scene.default_dt())} |")
    return EXIT_OK


def cmd_info(args):
    scene, sim = make_simulation(args)
    info = sim.info()
    print(f"scene       {scene.name}: {scene.description}")
    params = ", ".join(f"{k}={v}" for k, v in scene.params.items() if k != "mesh")
    if scene.form == "mesh":
        print(f"mesh        {scene.params['mesh']}: {params}")
    elif scene.form == "particles":
        print(f"model       hand-made ([particles] and [springs]): {params}")
    else:
        print(f"generator   {scene.generator}: {params}")
    print(f"size        {info['particles']} particles, {info['springs']} springs, "
          f"{sim.model.fixed.size} fixed" + (", moving" if sim.model.has_moving_pins else ""))
    if sim.model.has_colliders:
        print("colliders   " + "; ".join(f"{c.kind} (friction {c.friction:g}, restitution {c.restitution:g}"
                                         + (", moving" if c.moving else "") + ")" for c in sim.model.colliders))
    if sim.model.has_drag:
        print(f"air         drag {sim.model.drag:g} N s/m per particle, wind {sim.model.wind.tolist()} m/s")
    print(f"integrator  {sim.integrator}, dt = {format_seconds(sim.dt)}, precision {sim.precision}; "
          f"default duration {scene.duration:g} s")
    print("dt defaults " + ", ".join(f"{k} {format_seconds(scene.default_dt(k))}"
                                     + ("" if k in scene.dt else " (from the stability estimate)")
                                     for k in _integrator_names()))
    if info["preconditioner"] is not None:
        levels = info.get("levels")
        hierarchy = f" ({len(levels)} levels: {', '.join(f'{n:,}' for n in levels)} unknowns)" if levels else ""
        if info["newton"]:
            print(f"newton      until a step changes v by {sim.newton_tol:g} of the step's change, at most "
                  f"{sim.newton_max_iter} iterations, each a CG solve")
        print(f"solver      CG to {sim.cg_tol:g} (at most {sim.cg_max_iter:,} iterations), preconditioner "
              f"{sim.preconditioner}{hierarchy}, definiteness fix {'on' if sim.definiteness_fix else 'off'}")
    print(f"terms       {', '.join(info['terms'])}")
    print(f"arrays      {', '.join(info['arrays'])} ({info['bytes'] / 1e6:.2f} MB)")
    print(f"kernels     {info['loops']} loops")
    return EXIT_OK


def _integrator_names():
    from massspring.integrators import INTEGRATORS

    return tuple(INTEGRATORS)


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


def cmd_run(args):
    from massspring.errors import DivergenceError
    from massspring.io.files import check_writable
    from massspring.simulation import run

    scene, sim = make_simulation(args)
    start_steps = restart(args, scene, sim)
    steps = run_steps(args, scene, sim, start_steps)
    if args.out is not None:
        check_writable(args.out, "--out", (".npz",))
    frames = plan_frames(args, sim, steps)
    pictures = plan_pictures(args, scene, sim, steps, frames)
    export = plan_export(args, scene, sim, steps, frames)  # last: it creates the directory
    callbacks = [c for c in (pictures.recording.record if pictures else None, export) if c is not None]

    def on_frame(state):
        for callback in callbacks:
            callback(state)

    energy0 = sim.energy()
    start = time.perf_counter()
    stopped, diverged = None, None
    try:
        label = f"run {scene.name} ({sim.integrator}, dt {format_seconds(sim.dt)})"
        with progress.steps(label, steps, sim.dt, show=not args.quiet and steps > 1) as on_progress:
            run(sim, steps, frames=frames if callbacks else (), on_frame=on_frame if callbacks else None,
                progress=on_progress)
    except KeyboardInterrupt as exc:  # Ctrl-C or SIGTERM: the simulation holds the state reached
        stopped = exc
    except DivergenceError as exc:  # the simulation holds the last good state
        diverged = exc
    wall = time.perf_counter() - start
    with LateSignals() as late:  # from here a signal stops the rendering only, never a write
        if pictures is not None and (diverged or stopped):
            pictures.recording.record_last(sim)  # the picture ends on the last good state
        failed = write_outputs(args, scene, sim, start_steps + steps, pictures, late.arrived)
        if export is not None:
            failed += finish_export(export, sim, start_steps + steps, diverged, stopped)
        print_summary(scene, sim, wall, energy0, args.out if args.out and "--out" not in failed else None,
                      start_steps)
    done = sim.steps - start_steps
    if diverged is not None:
        print(f"massspring: {diverged}; {divergence_hint(sim, diverged)}", file=sys.stderr)
        return EXIT_DIVERGED
    if stopped is not None:
        what = "terminated" if isinstance(stopped, Terminated) else "interrupted"
        print(f"massspring: {what} after {done} of {steps} steps; the state reached so far "
              f"{'was written' if args.out and '--out' not in failed else 'is above'}", file=sys.stderr)
        return 128 + stopped.signum if isinstance(stopped, Terminated) else EXIT_INTERRUPTED
    if late.signum is not None:  # the run had ended; a signal cut the pictures short
        print(f"massspring: {'terminated' if late.signum == signal.SIGTERM else 'interrupted'} while writing the "
              "outputs; what was written is listed above", file=sys.stderr)
        return 128 + late.signum
    return EXIT_OUTPUT if failed else EXIT_OK


def restart(args, scene, sim):
    """With --restart, put the saved state into ``sim`` after checking that it belongs to
    this model and dt; returns the steps it had taken (0 without --restart)."""
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
    if state.dt != sim.dt:
        raise UsageError(f"--restart: {path} was computed with dt = {state.dt!r} s and this run's dt is "
                         f"{sim.dt!r} s; time is counted in steps of dt, so pass --dt {state.dt!r}")
    try:
        carried = state.carried if state.integrator == sim.integrator else None
        sim.set_state(state.positions, state.velocities, state.steps, carried)
    except ValueError as exc:
        raise UsageError(f"--restart: {path}: {exc}") from None
    return state.steps


class LateSignals:
    """While the outputs are written after a run: SIGINT and SIGTERM are recorded
    (``signum``, the first) instead of raising, so no file write is cut short; the
    rendering asks ``arrived()`` between frames and stops."""

    def __init__(self):
        self.signum, self.previous = None, {}

    def _record(self, signum, frame):
        self.signum = self.signum or signum

    def arrived(self):
        return self.signum is not None

    def __enter__(self):
        if _main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self.previous[sig] = signal.signal(sig, self._record)
        return self

    def __exit__(self, *exc):
        for sig, handler in self.previous.items():
            signal.signal(sig, handler)


def write_outputs(args, scene, sim, end_step, pictures, stop=None):
    """Write --out, then the pictures, each on its own: one failing does not stop the
    others (``end_step``: the step the run was to reach; ``stop()``: true when the
    rendering should end early). Returns the options whose output failed (each
    reported on stderr)."""
    from massspring.io.state import write_state

    failed = []
    if args.out:
        try:
            write_state(sim, args.out, scene.name)
        except OSError as exc:
            print(f"massspring: --out: could not write {args.out!r}: {exc.strerror or exc}", file=sys.stderr)
            failed.append("--out")
    if pictures is not None:
        failed += finish_pictures(pictures, scene, sim, end_step, stop)
    return failed


def divergence_hint(sim, exc):
    """What to try after a divergence, from the integrator and the stability estimate."""
    from massspring.analysis.stability import predict
    from massspring.integrators import INTEGRATORS

    if INTEGRATORS[sim.integrator].linear_solver:
        tips = ["a smaller --dt"]
        if not sim.definiteness_fix:
            tips.insert(0, "dropping --no-definiteness-fix")
        return "try " + " or ".join(tips)
    try:
        prediction = predict(sim.model, sim.model.positions)
    except (ValueError, ArithmeticError):
        return "try a smaller --dt or --integrator implicit"

    suggested = INTEGRATORS[sim.integrator].suggest_dt(prediction)
    if suggested >= sim.dt:  # the estimate at the initial state did not hold for this run
        return (f"try --dt {sim.dt / 4:.3g} (a quarter of this run's; the stability estimate for {sim.integrator} "
                f"at the initial state, {suggested:.3g} s, did not hold as the state changed) or --integrator "
                "implicit (no stability limit)")
    if sim.integrator == "explicit" and not prediction.explicit_stable_dt > 0:
        return (f"explicit Euler grows at every dt on this scene's undamped stiffest mode; --dt {suggested:.3g} "
                "keeps that growth under 2x per simulated second, or try --integrator symplectic or implicit")
    return (f"try --dt {suggested:.3g} (the stability estimate for {sim.integrator} at the initial state) "
            "or --integrator implicit (no stability limit)")


def add_export_arguments(p):
    from massspring.io.camera import FRAMINGS, PROJECTIONS
    from massspring.io.render import DEFAULT_FPS, DEFAULT_MAX_FRAMES, MAX_FPS

    g = p.add_argument_group("pictures (headless: no display, GPU or ffmpeg needed)")
    g.add_argument("--gif", metavar="PATH", help="write an animated GIF of the run (.gif)")
    g.add_argument("--png", metavar="PATH", help="write the final frame as a PNG (.png)")
    g.add_argument("--fps", type=float, help=f"GIF frames per second (default {DEFAULT_FPS}, at most {MAX_FPS}; "
                   "GIF stores whole 1/100 s per frame, so 30 plays at 33.3)")
    count = g.add_mutually_exclusive_group()
    count.add_argument("--frames", type=int, metavar="N", help="frames (of the GIF and of --export) from start "
                       f"to end (default: enough to play the simulated time in real time at --fps, at most "
                       f"{DEFAULT_MAX_FRAMES})")
    count.add_argument("--every", type=int, metavar="K", help="a frame every K steps (and the last step)")
    g.add_argument("--size", metavar="WxH", help="image size in pixels (default 480x480)")
    g.add_argument("--view", metavar="AZ,EL", help="camera azimuth and elevation in degrees "
                   "(default: the scene's [view])")
    g.add_argument("--projection", choices=PROJECTIONS, help="default: the scene's [view]")
    g.add_argument("--framing", choices=FRAMINGS, help="run: fit the whole run (default); follow: keep the "
                   "scale, centre each frame on the body; last: fit the last frame")


def add_frame_arguments(p):
    from massspring.io.frames import DEFAULT_FORMAT, FORMATS

    g = p.add_argument_group("frames as files (for Blender, ParaView, Houdini, Omniverse); sampled like the GIF")
    g.add_argument("--export", metavar="DIR", help="write the frames into DIR (created if missing), "
                   "with manifest.json")
    formats = "; ".join(f"{f.name}: {f.help}" + (f" (needs {f.module}: pip install 'massspring[{f.extra}]')"
                                                 if f.module else "") for f in FORMATS.values())
    g.add_argument("--format", choices=tuple(FORMATS), help=f"default {DEFAULT_FORMAT}; {formats}")


@dataclass
class PicturePlan:
    """What ``run --gif/--png`` records during the run and writes after it."""

    recording: object  # render.Recording
    view: object       # camera.View
    framing: str       # camera.FRAMINGS
    size: tuple
    fps: float
    gif: str | None
    png: str | None


def plan_frames(args, sim, steps):
    """The steps of this run (0..steps) at which --gif/--png record and --export writes a
    frame (``render.frame_steps``); None without any of them."""
    from massspring.io import render

    if not (args.gif or args.png or args.export):
        for name in ("fps", "frames", "every"):
            if getattr(args, name) is not None:
                raise UsageError(f"--{name}: only with --gif, --png or --export")
        return None
    fps = render.DEFAULT_FPS if args.fps is None else args.fps
    if not (math.isfinite(fps) and render.MIN_FPS <= fps <= render.MAX_FPS):
        raise UsageError(f"--fps: must be within {render.MIN_FPS:.4g}..{render.MAX_FPS} (a GIF frame lasts "
                         f"at most 655.35 s), got {fps:g}")
    try:
        return render.frame_steps(steps, frames=args.frames, every=args.every, duration=steps * sim.dt, fps=fps)
    except ValueError as exc:
        raise UsageError(f"--{exc}") from None  # "frames: ..." or "every: ..."


def plan_pictures(args, scene, sim, steps, steps_at):
    """Check the picture options before the run: None without --gif/--png."""
    from massspring.io import render
    from massspring.io.files import check_writable

    if not (args.gif or args.png):
        for name in ("gif", "png"):
            if getattr(args, name) == "":
                raise UsageError(f"--{name}: empty path")
        for name in ("size", "view", "projection", "framing"):
            if getattr(args, name) is not None:
                raise UsageError(f"--{name}: only with --gif or --png")
        return None
    for option, path, suffix in (("--gif", args.gif, ".gif"), ("--png", args.png, ".png")):
        if path is not None:
            check_writable(path, option, (suffix,))
    fps = render.DEFAULT_FPS if args.fps is None else args.fps
    size = parse_size(args.size or "480x480")
    view, framing = scene.view, args.framing or scene.framing
    if args.view is not None:
        parts = args.view.split(",")
        try:
            if len(parts) != 2:
                raise ValueError(f"expected AZ,EL in degrees, got {args.view!r}")
            view = replace(view, azimuth=_number(parts[0]), elevation=_number(parts[1]))
        except ValueError as exc:
            raise UsageError(f"--view: {exc}") from None
    if args.projection is not None:
        view = replace(view, projection=args.projection)
    check_kept_frames(len(steps_at), sim.model.n_particles, 12, "positions")
    return PicturePlan(render.Recording(), view, framing, size, fps, args.gif, args.png)


def check_kept_frames(frames, particles, size, what, limit=2e9):
    """Refuse a run whose ``frames`` would keep more than ``limit`` bytes in memory at
    ``size`` bytes per particle and frame (``what`` they are)."""
    need = frames * particles * size
    if need > limit:
        raise UsageError(f"--frames: {frames} frames of {particles} particles would keep {need / 1e9:.1f} GB of "
                         f"{what}; ask for fewer with --frames or --every")


def plan_export(args, scene, sim, steps, steps_at):
    """Check --export/--format before the run and create the directory: None without --export."""
    from massspring.io.frames import DEFAULT_FORMAT, FORMATS, FrameExport

    if not args.export:
        if args.export == "":
            raise UsageError("--export: empty path")
        if args.format is not None:
            raise UsageError("--format: only with --export")
        return None
    info = {"scene": {"name": scene.name, "source": scene.source, "form": scene.form,
                      "generator": scene.generator, "params": scene.params},
            "integrator": sim.integrator, "dt": sim.dt, "precision": sim.precision,
            "particles": sim.model.n_particles, "springs": sim.model.n_springs,
            "triangles": len(sim.model.triangles), "start_step": sim.steps, "end_step": sim.steps + steps}
    fmt = args.format or DEFAULT_FORMAT
    if FORMATS[fmt].single_file:  # its frames stay in memory until the run ends
        check_kept_frames(len(steps_at), sim.model.n_particles, 24, "positions and velocities")
    export = FrameExport(args.export, fmt, len(steps_at), scene.name, info)
    export.prepare()
    return export


def finish_export(export, sim, end_step, diverged, stopped):
    """Mark the manifest with how the run ended and say what was written (on stderr if
    the run stopped early or a file failed). Returns ["--export"] if a file failed."""
    if diverged is not None:
        status, message = "diverged", str(diverged)
    elif stopped is not None:
        status = "terminated" if isinstance(stopped, Terminated) else "interrupted"
        message = f"{status} after step {sim.steps}"
    else:
        status, message = "complete", ""
    error = export.finish(status, sim, message)
    where = f"{len(export)} {export.fmt} frame(s) in {str(export.directory)!r} (see manifest.json)"
    if error is not None:
        print(f"massspring: --export: {error}; {where}", file=sys.stderr)
        return ["--export"]
    if status != "complete":
        print(f"massspring: the run stopped at step {sim.steps} of {end_step}; wrote {where}, the frames up to "
              "then", file=sys.stderr)
    else:
        print(f"frames      wrote {where}")
    return []


def parse_size(text):
    """'WxH' -> (W, H) in pixels, each within 64..4096."""
    w, sep, h = text.lower().partition("x")
    try:
        size = (int(w), int(h))
    except ValueError:
        size = None
    if not sep or size is None or not all(64 <= v <= 4096 for v in size):
        raise UsageError(f"--size: expected WxH with W and H within 64..4096 pixels, got {text!r}")
    return size


def _number(text):
    try:
        return float(text)
    except ValueError:
        raise ValueError(f"expected a number, got {text.strip()!r}") from None


def finish_pictures(plan, scene, sim, end_step, stop=None):
    """Render what was recorded, write the GIF/PNG and say what was written (on stderr
    if the run or the rendering stopped early). Returns the options whose file failed."""
    from massspring.io import render

    rec = plan.recording
    early = sim.steps < end_step
    if not len(rec):
        print("massspring: no frame was recorded: nothing written to " +
              " or ".join(p for p in (plan.gif, plan.png) if p), file=sys.stderr)
        return []
    start = time.perf_counter()
    renderer = render.FrameRenderer(sim.model, np.stack(rec.positions), plan.view, plan.size,
                                    label=f"{scene.name}  {sim.integrator}  dt = {format_seconds(sim.dt)}",
                                    framing=plan.framing, times=rec.times)
    result = render.export(renderer, rec, gif=plan.gif, png=plan.png, fps=plan.fps, stop=stop)
    wall = time.perf_counter() - start
    for option, error in result.errors.items():
        print(f"massspring: {option}: could not write: {error}", file=sys.stderr)
    written = " and ".join(p for option, p in (("--gif", plan.gif), ("--png", plan.png))
                           if p and option not in result.errors)
    if not result.count or not written:
        if result.interrupted:
            print("massspring: rendering interrupted before the first frame: nothing written", file=sys.stderr)
        return list(result.errors)
    last = rec.times[result.count - 1] if plan.gif else rec.times[-1]
    note = (f"{written}: {result.count} frame(s) of {plan.size[0]}x{plan.size[1]}, t = {rec.times[0]:g} to "
            f"{last:g} s, rendered in {wall:.2f} s ({1e3 * wall / result.count:.1f} ms/frame)")
    if plan.gif and "--gif" not in result.errors:
        note += f"; the GIF plays at {render.gif_delay(plan.fps)[1]:g} frames/s"
    if rec.skipped:
        note += f"; {rec.skipped} frame(s) with non-finite positions left out"
    if result.interrupted:
        print(f"massspring: rendering interrupted; wrote the frames rendered so far: {note}", file=sys.stderr)
    elif early:
        print(f"massspring: the run stopped at step {sim.steps} of {end_step}; wrote the frames recorded up to "
              f"then: {note}", file=sys.stderr)
    else:
        print(f"pictures    wrote {note}")
    return list(result.errors)


def print_summary(scene, sim, wall, energy0, out, start_steps=0):
    info = sim.info()
    energy1 = sim.energy()
    done = sim.steps - start_steps
    rate = done / wall if wall > 0 else float("inf")
    print(f"scene       {scene.name} ({info['particles']} particles, {info['springs']} springs)")
    print(f"integrator  {sim.integrator}, dt = {format_seconds(sim.dt)}, {sim.precision}")
    if start_steps:
        print(f"steps       {done} from the restart at step {start_steps} to step {sim.steps} (t = "
              f"{start_steps * sim.dt:g} to {sim.time:g} s) in {wall:.2f} s wall, {rate:.1f} steps/s")
    else:
        print(f"steps       {sim.steps} ({sim.time:g} s simulated) in {wall:.2f} s wall, {rate:.1f} steps/s")
    if sim.newton_iterations:
        newton = np.array(sim.newton_iterations)
        print(f"Newton      {newton.mean():.2f} iterations/step mean, {newton.max()} max, {sim.line_search_cuts} "
              f"line-search cut(s), {sim.cg_failures} step(s) not converged (tol {sim.newton_tol:g})")
    if sim.cg_iterations:
        its = np.array(sim.cg_iterations)
        failed = "" if sim.newton_iterations else f", {sim.cg_failures} step(s) not converged"
        print(f"CG          {its.mean():.1f} iterations/step mean, {its.max()} max{failed} (tol {sim.cg_tol:g}, "
              f"{sim.preconditioner})")
        if sim.cg_failures and sim.precision == "f32":
            print("note        f32 CG stalls where round-off stops the residual, 1e-5 to 1e-4 relative "
                  "on a cloth at rest: use --cg-tol 1e-3 or --precision f64")
        if sim.cg_failures and not sim.definiteness_fix:
            print("note        CG stops when A is indefinite, as compressed springs make it without the "
                  "definiteness fix: drop --no-definiteness-fix")
    print("energy      " + format_energy(energy0, energy1))
    print(f"compiled    terms: {', '.join(info['terms'])}; arrays: {', '.join(info['arrays'])} "
          f"({info['loops']} loops)")
    if out:
        print(f"wrote       {out}")


def format_energy(start, end):
    """Energies (J) at a precision that matches what they mean: each to 4 significant
    digits, and 0 where it is round-off (below 1e-12 of the largest energy involved)."""
    scale = max(abs(v) for e in (start, end) for v in e.values()) or 1.0

    def fmt(value):
        return "0" if abs(value) <= 1e-12 * scale else f"{value:.4g}"

    return (f"start {fmt(start['total'])} J, end {fmt(end['total'])} J (kinetic {fmt(end['kinetic'])}, "
            f"spring {fmt(end['spring'])}, gravity {fmt(end['gravity'])})")


def add_study_arguments(p):
    p.add_argument("scene", help="a built-in scene name (see `massspring scenes`) or a TOML file")
    p.add_argument("--out", help="output directory (default: a new ./study-SCENE)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a scene model parameter (repeatable)")
    p.add_argument("--duration", type=float, help="simulated end time in s (default: a tenth of the scene's)")
    p.add_argument("--integrators", default="explicit,symplectic,implicit", help="comma-separated list")
    p.add_argument("--rungs", type=int, default=7, help="dt values per line, a factor of 2 apart (default 7)")
    p.add_argument("--cg-tols", default="1e-2,1e-4,1e-6", help="implicit: comma-separated CG tolerances")
    p.add_argument("--newton-tols", default="1e-3,1e-6", help="backward-euler, bdf2: comma-separated Newton "
                   "tolerances")
    p.add_argument("--preconditioners", default="auto",
                   help="implicit: comma-separated preconditioners, a line each (auto, block-jacobi, multigrid, "
                   "none; default auto)")
    p.add_argument("--repeats", type=int, default=3, help="timed runs per configuration, at most (default 3)")
    p.add_argument("--cache-dir", help="RK4 reference cache (default $MASSSPRING_CACHE, "
                   "else $XDG_CACHE_HOME/massspring or ~/.cache/massspring)")
    add_cluster_arguments(p)


# run_study's arguments -> the options of `massspring study` that give them
STUDY_OPTIONS = {"integrators": "--integrators", "duration": "--duration", "rungs": "--rungs",
                 "cg_tols": "--cg-tols", "newton_tols": "--newton-tols", "preconditioners": "--preconditioners",
                 "repeats": "--repeats"}


def cmd_study(args):
    from massspring.analysis import cluster, report, study
    from massspring.scene import load_scene

    scene = load_scene(args.scene).with_settings(args.set)
    out = Path(args.out) if args.out else report.new_out_dir(scene.name)
    if out.exists() and not out.is_dir():
        raise UsageError(f"--out: {str(out)!r} exists and is not a directory")
    tols = {}
    for key in ("cg_tols", "newton_tols"):
        try:
            tols[key] = [_number(text) for text in filter(str.strip, getattr(args, key).split(","))]
        except ValueError as exc:
            raise UsageError(f"--{key.replace('_', '-')}: {exc}") from None
    try:
        cluster.check_options(args.workers, args.address)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    try:
        with cluster.cluster(args.workers, args.address) as client:
            result = study.run_study(
                scene, integrators=[s.strip() for s in args.integrators.split(",") if s.strip()],
                duration=args.duration, rungs=args.rungs, **tols,
                preconditioners=[s.strip() for s in args.preconditioners.split(",") if s.strip()],
                repeats=args.repeats, cache=args.cache_dir, progress=report.print_progress, client=client)
    except ValueError as exc:  # run_study checks its arguments first: name them as options
        name, _, reason = str(exc).partition(": ")
        if name in STUDY_OPTIONS:
            raise UsageError(f"{STUDY_OPTIONS[name]}: {reason}") from None
        raise
    print(report.report(result))
    written = report.write_outputs(result, out)
    try:
        written.append(report.plot(result, out / "work_precision.png"))
    except ImportError:
        print("plot skipped: matplotlib is not installed (pip install 'massspring[plot]')")
    print("wrote " + ", ".join(str(p) for p in written))
    return EXIT_OK


def add_stability_arguments(p, integrators):
    add_scene_arguments(p, integrators)
    p.add_argument("--out", help="write PREFIX.csv, PREFIX.json and PREFIX.png (default: ./stability-SCENE)")
    p.add_argument("--run-duration", type=float, default=1.0,
                   help="simulated seconds per ladder run, capped by --max-steps (default 1)")
    p.add_argument("--max-steps", type=int, default=1000, help="step cap per ladder run (default 1000)")
    p.add_argument("--at", type=float, default=0.0, metavar="SECONDS",
                   help="predict at the state the implicit integrator reaches after SECONDS (default 0: "
                   "the initial state)")
    p.add_argument("--predict-only", action="store_true", help="print the predictions, run no ladder")
    add_cluster_arguments(p)


def cmd_stability(args):
    from massspring.analysis import cluster, stability
    from massspring.scene import load_scene

    for name in ("run_duration", "at"):
        value = getattr(args, name)
        ok = math.isfinite(value) and (value >= 0 if name == "at" else value > 0)
        if not ok:
            raise UsageError(f"--{name.replace('_', '-')}: must be a finite number "
                             f"{'>= 0' if name == 'at' else '> 0'}, got {value}")
    if not 1 <= args.max_steps <= MAX_STEPS:
        raise UsageError(f"--max-steps: must be within 1..{MAX_STEPS}, got {args.max_steps}")
    if args.integrator or args.dt is not None or args.no_definiteness_fix:
        raise UsageError("--integrator/--dt/--no-definiteness-fix: the ladder runs every integrator "
                         "at its own dts, implicit with the fix on and off")
    try:
        cluster.check_options(args.workers, args.address)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    scene = load_scene(args.scene).with_settings(args.set)
    prefix = Path(args.out) if args.out else Path(f"stability-{scene.name}")
    if not prefix.parent.is_dir():
        raise UsageError(f"--out: directory {str(prefix.parent)!r} does not exist")
    options = dict(precision=args.precision, **solver_options(args))
    model, positions = scene.model(), None
    if args.at > 0:
        settle = scene.simulation("implicit", **options)
        steps = args.at / settle.dt
        if not steps <= MAX_STEPS:
            raise UsageError(f"--at: {args.at:g} s at the implicit dt {format_seconds(settle.dt)} is {steps:.3g} steps, "
                             f"more than {MAX_STEPS:.3g}")
        settle.step(max(1, round(steps)))
        positions = settle.positions
        settle.close()
    prediction = stability.predict(model, positions)
    print("\n".join(stability.prediction_lines(prediction, scene.name)))
    if args.predict_only:
        return EXIT_OK
    print(f"ladder: each run min({args.run_duration:g} s, {args.max_steps} steps); implicit with the "
          "definiteness fix on and off; the scene's default dt last in each group")
    if progress.interactive(sys.stderr):
        def on_row(row):
            print(".", end="", file=sys.stderr, flush=True)
    else:
        def on_row(row):
            fix = "" if row["definiteness_fix"] in (None, True) else " without the definiteness fix"
            print(f"stability {scene.name}: {row['integrator']}{fix} dt {row['dt']:.4g}: {row['outcome']}",
                  file=sys.stderr, flush=True)
    with cluster.cluster(args.workers, args.address) as client:
        rows = stability.ladder(scene, prediction, duration=args.run_duration, max_steps=args.max_steps,
                                progress=on_row, client=client, **options)
    if progress.interactive(sys.stderr):
        print(file=sys.stderr)
    print(stability.format_table(rows))
    written = stability.write_outputs(rows, prediction, scene.name, prefix)
    try:
        written.append(stability.plot(rows, f"{prefix}.png", f"{scene.name}: stability ladder"))
    except ImportError:
        print("plot skipped: matplotlib is not installed (pip install 'massspring[plot]')")
    print("wrote " + ", ".join(str(p) for p in written))
    return EXIT_OK


def add_cluster_arguments(p):
    where = p.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, metavar="N", help="run the cases on a local Dask cluster of N "
                       "worker processes, started for this command (pip install 'massspring[cluster]')")
    where.add_argument("--address", metavar="tcp://HOST:PORT",
                       help="run the cases on the Dask cluster whose scheduler listens there")


def add_sweep_arguments(p, integrators):
    from massspring.analysis.sweep import MAX_CASES, METRICS

    add_scene_arguments(p, integrators)
    p.add_argument("--vary", action="append", default=[], metavar="KEY=V1,V2,...", required=True,
                   help="a model parameter (as --set), dt, integrator or preconditioner and its values; "
                   "repeatable: one case per combination")
    length = p.add_mutually_exclusive_group()
    length.add_argument("--steps", type=int, help="steps per case (default: the scene's duration / dt)")
    length.add_argument("--duration", type=float, help="simulated seconds per case (default: the scene's)")
    p.add_argument("--out", required=True, help="the CSV: a row per case, appended as each finishes; "
                   "an existing one of the same sweep is resumed (its finished cases are skipped)")
    p.add_argument("--states", metavar="DIR", help="keep each case's final state as DIR/caseNNNN.npz")
    p.add_argument("--plot", metavar="PNG", help="draw --metric against the first varied key (a line per "
                   "value of the second) (pip install 'massspring[plot]')")
    p.add_argument("--metric", choices=METRICS, default="energy", help="what --plot draws (default energy)")
    p.add_argument("--yes", action="store_true", help=f"run more than {MAX_CASES} cases")
    p.add_argument("--quiet", action="store_true", help="no line per finished case")
    add_cluster_arguments(p)


def cmd_sweep(args):
    from massspring.analysis import cluster, sweep
    from massspring.device import ensure_taichi
    from massspring.io.files import check_writable
    from massspring.scene import load_scene

    scene = load_scene(args.scene).with_settings(args.set)
    try:
        vary = sweep.parse_vary(args.vary)
        cases = sweep.plan(scene, vary, integrator=args.integrator, confirm=args.yes, option="--vary")
        for name in ("dt", "duration"):
            if getattr(args, name) is not None:
                validate.positive_float(f"--{name}", getattr(args, name))
        if args.duration is not None:
            sweep.check_duration(scene, cases, args.duration, args.integrator, args.dt, "--duration")
        if args.steps is not None and not 1 <= args.steps <= MAX_STEPS:
            raise ValueError(f"--steps: must be within 1..{MAX_STEPS}, got {args.steps}")
        check_writable(args.out, "--out", (".csv",))
        if args.states is not None and not Path(args.states).is_dir():
            raise ValueError(f"--states: {args.states!r} is not a directory")
        if args.plot is not None:
            check_writable(args.plot, "--plot", (".png",))
            if len(vary) > 2:
                raise ValueError(f"--plot: draws against one or two varied keys, not {len(vary)}")
            _needs_matplotlib("--plot")
        cluster.check_options(args.workers, args.address)
        ensure_taichi(args.arch, "--arch")
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    options = dict(precision=args.precision, arch=args.arch, **solver_options(args))
    total = len(cases)
    finished = []

    def on_case(case, row):
        finished.append(row)
        if not args.quiet:
            message = f": {row['message']}" if row["message"] else ""
            print(f"sweep {scene.name}: case {case.number} of {total} ({case.label()}): {row['status']} in "
                  f"{row['wall_s']:.2f} s{message}", file=sys.stderr, flush=True)

    if not args.quiet and Path(args.out).exists():
        print(f"sweep {scene.name}: resuming {args.out}: its finished cases are skipped", file=sys.stderr)
    try:
        with cluster.cluster(args.workers, args.address) as client:
            rows = sweep.sweep(scene, vary, integrator=args.integrator, dt=args.dt, duration=args.duration,
                               steps=args.steps, out=args.out, states=args.states, client=client,
                               options=options, confirm=args.yes, progress=on_case)
    except KeyboardInterrupt as exc:
        what = "terminated" if isinstance(exc, Terminated) else "interrupted"
        print(f"massspring: {what} after {len(finished)} new case(s); {args.out} holds every finished one",
              file=sys.stderr)
        return 128 + exc.signum if isinstance(exc, Terminated) else EXIT_INTERRUPTED
    print(sweep.format_table(rows, list(vary)))
    written = [args.out]
    if args.plot is not None:
        written.append(sweep.plot(rows, list(vary), args.metric, args.plot, f"{scene.name}: {args.metric}"))
    print("wrote " + ", ".join(str(p) for p in written))
    return EXIT_OK


def _needs_matplotlib(option):
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        raise ValueError(f"{option}: matplotlib is not installed (pip install 'massspring[plot]')") from None


COMMANDS = {"run": cmd_run, "scenes": cmd_scenes, "info": cmd_info, "study": cmd_study,
            "stability": cmd_stability, "sweep": cmd_sweep}


def _terminate(signum, frame):
    raise Terminated(signum)


def joined_values(argv):
    """``argv`` with ``--view AZ,EL`` written as ``--view=AZ,EL`` when AZ is negative:
    argparse takes a value starting with "-" that is not a plain number for an option."""
    out = []
    for arg in argv:
        if out and out[-1] == "--view" and arg.startswith("-") and "," in arg:
            out[-1] = f"--view={arg}"
        else:
            out.append(arg)
    return out


def main(argv=None):
    parser, verbs = build_parser()
    args, unknown = parser.parse_known_args(joined_values(sys.argv[1:] if argv is None else argv))
    if unknown:  # a misspelt option after a verb: that verb's usage, not the top-level one
        verbs[args.command].error(f"unrecognized arguments: {' '.join(unknown)}")
    previous = signal.signal(signal.SIGTERM, _terminate) if _main_thread() else None
    try:
        return COMMANDS[args.command](args)
    except ValueError as exc:  # SceneError, UsageError and Model/Simulation validation
        print(f"massspring: error: {clipped(str(exc))}", file=sys.stderr)
        return EXIT_USAGE
    except Terminated as exc:  # SIGTERM outside a run (e.g. while loading)
        return 128 + exc.signum
    except BrokenPipeError:  # output piped into e.g. `head`
        sys.stderr.close()
        return EXIT_OK
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def _main_thread():
    import threading

    return threading.current_thread() is threading.main_thread()


if __name__ == "__main__":
    sys.exit(main())
