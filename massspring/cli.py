"""The ``massspring`` command line: run built-in or user scenes, list them, describe them.

Exit codes: 0 success; 2 bad usage or bad scene/input (one line on stderr, no
traceback); 3 the simulation diverged (one line on stderr; the last good state is
still summarised and written); 130 interrupted (the state reached so far is still written).
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

EXIT_OK, EXIT_USAGE, EXIT_DIVERGED, EXIT_INTERRUPTED = 0, 2, 3, 130


class UsageError(ValueError):
    """Bad command-line input; reported in one line with exit code 2."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="massspring", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    run = sub.add_parser("run", help="run a scene and print a summary")
    add_scene_arguments(run)
    length = run.add_mutually_exclusive_group()
    length.add_argument("--steps", type=int, help="number of steps (default: the scene's duration / dt)")
    length.add_argument("--duration", type=float, help="simulated seconds (default: the scene's)")
    run.add_argument("--out", help="write the final state to this .npz file")
    run.add_argument("--quiet", action="store_true", help="no progress bar")
    add_export_arguments(run)

    sub.add_parser("scenes", help="list the built-in scenes")

    info = sub.add_parser("info", help="show a scene's size, defaults, and what a run compiles")
    add_scene_arguments(info)

    stab = sub.add_parser("stability", help="predict each integrator's dt limit from the spectrum, "
                          "then run a ladder of dt around it")
    add_stability_arguments(stab)

    study = sub.add_parser("study", help="work-precision study: error against run time per integrator and dt")
    add_study_arguments(study)
    return parser


def add_scene_arguments(p):
    p.add_argument("scene", help="a built-in scene name (see `massspring scenes`) or a TOML file")
    p.add_argument("--integrator", choices=("explicit", "symplectic", "implicit"),
                   help="time integrator (default: the scene's)")
    p.add_argument("--dt", type=float, help="time step in s (default: the scene's for the integrator)")
    p.add_argument("--precision", choices=("f64", "f32"), default="f64")
    p.add_argument("--arch", default="cpu", help="Taichi arch: cpu (default), cuda, vulkan, metal, gpu ...")
    p.add_argument("--cg-tol", type=float, default=1e-6, help="implicit: relative CG tolerance (default 1e-6)")
    p.add_argument("--cg-max-iter", type=int, help="implicit: CG iteration limit per step "
                   "(default 3 x free particles, at least 100)")
    p.add_argument("--no-definiteness-fix", action="store_true",
                   help="implicit: use the seed's Eq. 13 as written (may be indefinite when compressed)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a scene model parameter, e.g. --set resolution=64 (repeatable)")


def make_simulation(args):
    """Scene + options -> (scene, Simulation); raises ValueError on bad input before any kernel runs."""
    from massspring.scene import load_scene

    scene = load_scene(args.scene).with_settings(args.set)
    sim = scene.simulation(integrator=args.integrator, dt=args.dt, precision=args.precision,
                           cg_tol=args.cg_tol, cg_max_iter=args.cg_max_iter,
                           definiteness_fix=not args.no_definiteness_fix, arch=args.arch)
    return scene, sim


def cmd_scenes(args):
    from massspring.scene import builtin_scenes, load_scene

    for name in sorted(builtin_scenes()):
        print(f"{name:10s} {load_scene(name).description}")
    return EXIT_OK


def cmd_info(args):
    scene, sim = make_simulation(args)
    info = sim.info()
    print(f"scene       {scene.name}: {scene.description}")
    print(f"generator   {scene.generator}: " + ", ".join(f"{k}={v}" for k, v in scene.params.items()))
    print(f"size        {info['particles']} particles, {info['springs']} springs, "
          f"{sim.model.fixed.size} fixed")
    print(f"integrator  {sim.integrator}, dt = {sim.dt:g} s, precision {sim.precision}; "
          f"default duration {scene.duration:g} s")
    print("dt defaults " + ", ".join(f"{k} {v:g}" for k, v in scene.dt.items()))
    print(f"terms       {', '.join(info['terms'])}")
    print(f"arrays      {', '.join(info['arrays'])} ({info['bytes'] / 1e6:.2f} MB)")
    print(f"kernels     {info['storage']}s, {info['loops']} loops")
    return EXIT_OK


def cmd_run(args):
    scene, sim = make_simulation(args)
    if args.steps is not None:
        if args.steps < 0:
            raise UsageError(f"--steps: must be >= 0, got {args.steps}")
        steps = args.steps
    else:
        duration = scene.duration if args.duration is None else args.duration
        if not duration > 0:
            raise UsageError(f"--duration: must be > 0, got {duration}")
        steps = max(1, int(round(duration / sim.dt)))
    if args.out and not Path(args.out).parent.is_dir():
        raise UsageError(f"--out: directory {str(Path(args.out).parent)!r} does not exist")

    export = plan_export(args, scene, sim, steps)

    from massspring.errors import DivergenceError

    energy0 = sim.energy()
    start = time.perf_counter()
    interrupted, diverged = False, None
    try:
        advance(sim, steps, show=not args.quiet and steps > 1, frames=export and export.recording.steps,
                on_frame=export and export.recording.record)
    except KeyboardInterrupt:
        interrupted = True
    except DivergenceError as exc:  # the simulation holds the last good state
        diverged = exc
    finally:  # however the run ends (Ctrl-C, divergence, any error), write what was recorded
        wall = time.perf_counter() - start
        if export is not None:
            interrupted = finish_export(export, scene, sim, steps) or interrupted
    if args.out:
        write_state(sim, args.out)
    print_summary(scene, sim, wall, energy0, args.out)
    if diverged is not None:
        print(f"massspring: {diverged}", file=sys.stderr)
        return EXIT_DIVERGED
    if interrupted:
        print(f"massspring: interrupted after {sim.steps} of {steps} steps; "
              f"the state reached so far{' was written' if args.out else ' is above'}", file=sys.stderr)
        return EXIT_INTERRUPTED
    return EXIT_OK


def advance(sim, steps, show=True, frames=None, on_frame=None):
    """Step ``sim`` by ``steps`` in chunks, with a progress bar on stderr when ``show``.

    With ``on_frame``, ``on_frame(sim)`` is called each time the steps taken here reach
    an entry of ``frames`` (sorted ints in 0..steps; 0 is before the first step), and
    chunks end there. Without it the run steps exactly as it would otherwise.
    """
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    chunk = max(1, steps // 200)
    with Progress(TextColumn("[progress.description]{task.description}"), BarColumn(),
                  TextColumn("{task.completed}/{task.total} steps"), TimeElapsedColumn(),
                  TimeRemainingColumn(), transient=True, disable=not show,
                  console=Console(stderr=True)) as bar:
        task = bar.add_task(f"{sim.integrator} dt={sim.dt:g}", total=steps)
        pending = list(frames) if on_frame is not None else []
        done = next_frame = 0
        while True:
            while next_frame < len(pending) and pending[next_frame] <= done:
                if pending[next_frame] == done:
                    on_frame(sim)
                next_frame += 1
            if done >= steps:
                break
            k = min(chunk, steps - done)
            if next_frame < len(pending):
                k = min(k, pending[next_frame] - done)
            sim.step(k)
            done += k
            bar.update(task, completed=done)


def write_state(sim, path):
    """Write positions, velocities, springs and time to ``path`` (.npz) atomically."""
    from massspring.files import atomic_output

    with atomic_output(path) as fh:
        np.savez(fh, positions=sim.positions, velocities=sim.velocities,
                 springs=sim.model.springs, time=sim.time, steps=sim.steps, dt=sim.dt)


def add_export_arguments(p):
    from massspring.render import DEFAULT_MAX_FRAMES, MAX_FPS, PROJECTIONS

    g = p.add_argument_group("pictures (headless: no display, GPU or ffmpeg needed)")
    g.add_argument("--gif", metavar="PATH", help="write an animated GIF of the run")
    g.add_argument("--png", metavar="PATH", help="write the final frame as a PNG")
    g.add_argument("--fps", type=float, help=f"GIF frames per second (default 30, at most {MAX_FPS})")
    count = g.add_mutually_exclusive_group()
    count.add_argument("--frames", type=int, metavar="N", help="frames from start to end (default: enough to "
                       f"play the simulated time in real time at --fps, at most {DEFAULT_MAX_FRAMES})")
    count.add_argument("--every", type=int, metavar="K", help="a frame every K steps (and the last step)")
    g.add_argument("--size", metavar="WxH", help="image size in pixels (default 480x480)")
    g.add_argument("--view", metavar="AZ,EL", help="camera azimuth and elevation in degrees "
                   "(default: the scene's [view])")
    g.add_argument("--projection", choices=PROJECTIONS, help="default: the scene's [view]")


@dataclass
class ExportPlan:
    """What ``run --gif/--png`` records during the run and writes after it."""

    recording: object  # render.Recording
    view: object       # render.View
    size: tuple
    fps: float
    gif: str | None
    png: str | None


def plan_export(args, scene, sim, steps):
    """Check the picture options before the run: None without --gif/--png."""
    from massspring import render

    if not (args.gif or args.png):
        for name in ("fps", "frames", "every", "size", "view", "projection"):
            if getattr(args, name) is not None:
                raise UsageError(f"--{name}: only with --gif or --png")
        return None
    for option, path in (("--gif", args.gif), ("--png", args.png)):
        if path and not Path(path).parent.is_dir():
            raise UsageError(f"{option}: directory {str(Path(path).parent)!r} does not exist")
    fps = 30.0 if args.fps is None else args.fps
    if not 0 < fps <= render.MAX_FPS:
        raise UsageError(f"--fps: must be > 0 and <= {render.MAX_FPS}, got {fps:g}")
    size = parse_size(args.size or "480x480")
    view = scene.view
    try:
        if args.view is not None:
            parts = args.view.split(",")
            if len(parts) != 2:
                raise ValueError(f"expected AZ,EL in degrees, got {args.view!r}")
            view = replace(view, azimuth=_number(parts[0]), elevation=_number(parts[1]))
        if args.projection is not None:
            view = replace(view, projection=args.projection)
    except ValueError as exc:
        raise UsageError(f"--view: {exc}") from None
    try:
        steps_at = render.frame_steps(steps, frames=args.frames, every=args.every, duration=steps * sim.dt, fps=fps)
    except ValueError as exc:
        raise UsageError(f"--{exc}") from None  # "frames: ..." or "every: ..."
    need = len(steps_at) * sim.model.n_particles * 12
    if need > 2e9:
        raise UsageError(f"--frames: {len(steps_at)} frames of {sim.model.n_particles} particles would keep "
                         f"{need / 1e9:.1f} GB of positions; ask for fewer with --frames or --every")
    return ExportPlan(render.Recording(steps_at), view, size, fps, args.gif, args.png)


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


def finish_export(plan, scene, sim, steps):
    """Render what was recorded, write the GIF/PNG and say what was written (on stderr
    if the run or the rendering stopped early). Returns True if Ctrl-C stopped the rendering."""
    from massspring import render

    rec = plan.recording
    early = sim.steps < steps
    if not len(rec):
        print("massspring: no frame was recorded: nothing written to " +
              " or ".join(p for p in (plan.gif, plan.png) if p), file=sys.stderr)
        return False
    start = time.perf_counter()
    renderer = render.FrameRenderer(sim.model, np.stack(rec.positions), scene.triangles(), plan.view, plan.size,
                                    label=f"{scene.name}  {sim.integrator}  dt = {sim.dt:g} s")
    count, interrupted = render.export(renderer, rec, gif=plan.gif, png=plan.png, fps=plan.fps)
    wall = time.perf_counter() - start
    if count == 0:
        print("massspring: rendering interrupted before the first frame: nothing written", file=sys.stderr)
        return interrupted
    written = " and ".join(p for p in (plan.gif, plan.png) if p)
    last = rec.times[count - 1] if plan.gif else rec.times[-1]
    note = (f"{written}: {count} frame(s) of {plan.size[0]}x{plan.size[1]}, t = {rec.times[0]:g} to {last:g} s, "
            f"rendered in {wall:.2f} s ({1e3 * wall / count:.1f} ms/frame)")
    if rec.skipped:
        note += f"; {rec.skipped} frame(s) with non-finite positions left out"
    if interrupted:
        print(f"massspring: rendering interrupted; wrote the frames rendered so far: {note}", file=sys.stderr)
    elif early:
        print(f"massspring: the run stopped at step {sim.steps} of {steps}; wrote the frames recorded up to "
              f"then: {note}", file=sys.stderr)
    else:
        print(f"pictures    wrote {note}")
    return interrupted


def print_summary(scene, sim, wall, energy0, out):
    info = sim.info()
    energy1 = sim.energy()
    rate = sim.steps / wall if wall > 0 else float("inf")
    print(f"scene       {scene.name} ({info['particles']} particles, {info['springs']} springs)")
    print(f"integrator  {sim.integrator}, dt = {sim.dt:g} s, {sim.precision}")
    print(f"steps       {sim.steps} ({sim.time:g} s simulated) in {wall:.2f} s wall, {rate:.1f} steps/s")
    if sim.integrator == "implicit" and sim.cg_iterations:
        its = np.array(sim.cg_iterations)
        print(f"CG          {its.mean():.1f} iterations/step mean, {its.max()} max, "
              f"{sim.cg_failures} step(s) not converged (tol {sim.cg_tol:g})")
        if sim.cg_failures and sim.precision == "f32":
            print("note        f32 CG stalls near a relative residual of 1e-5 (round-off): "
                  "use --cg-tol 1e-4 or --precision f64")
    print(f"energy      start {energy0['total']:.6g} J, end {energy1['total']:.6g} J "
          f"(kinetic {energy1['kinetic']:.4g}, spring {energy1['spring']:.4g}, gravity {energy1['gravity']:.4g})")
    print(f"compiled    terms: {', '.join(info['terms'])}; arrays: {', '.join(info['arrays'])} "
          f"({info['storage']}s, {info['loops']} loops)")
    if out:
        print(f"wrote       {out}")


def add_study_arguments(p):
    p.add_argument("scene", help="a built-in scene name (see `massspring scenes`) or a TOML file")
    p.add_argument("--out", help="output directory (default: a new ./study-SCENE)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a scene model parameter (repeatable)")
    p.add_argument("--duration", type=float, help="simulated end time in s (default: a tenth of the scene's)")
    p.add_argument("--integrators", default="explicit,symplectic,implicit", help="comma-separated list")
    p.add_argument("--rungs", type=int, default=7, help="dt values per line, a factor of 2 apart (default 7)")
    p.add_argument("--cg-tols", default="1e-2,1e-4,1e-6", help="implicit: comma-separated CG tolerances")
    p.add_argument("--repeats", type=int, default=3, help="timed runs per configuration, at most (default 3)")
    p.add_argument("--cache-dir", help="RK4 reference cache (default $MASSSPRING_CACHE, "
                   "else $XDG_CACHE_HOME/massspring or ~/.cache/massspring)")


def cmd_study(args):
    from massspring import study
    from massspring.scene import load_scene

    scene = load_scene(args.scene).with_settings(args.set)
    out = Path(args.out) if args.out else study.new_out_dir(scene.name)
    if out.exists() and not out.is_dir():
        raise UsageError(f"--out: {str(out)!r} exists and is not a directory")
    try:
        tols = [float(t) for t in args.cg_tols.split(",") if t.strip()]
    except ValueError:
        raise UsageError(f"--cg-tols: expected comma-separated numbers, got {args.cg_tols!r}") from None
    result = study.run_study(scene, integrators=[s.strip() for s in args.integrators.split(",") if s.strip()],
                             duration=args.duration, rungs=args.rungs, cg_tols=tols, repeats=args.repeats,
                             cache=args.cache_dir, progress=study.print_progress)
    print(study.report(result))
    written = study.write_outputs(result, out)
    try:
        written.append(study.plot(result, out / "work_precision.png"))
    except ImportError:
        print("plot skipped: matplotlib is not installed (pip install 'massspring[plot]')")
    print("wrote " + ", ".join(str(p) for p in written))
    return EXIT_OK


def add_stability_arguments(p):
    add_scene_arguments(p)
    p.add_argument("--out", help="write PREFIX.csv, PREFIX.json and PREFIX.png (default: ./stability-SCENE)")
    p.add_argument("--run-duration", type=float, default=1.0,
                   help="simulated seconds per ladder run, capped by --max-steps (default 1)")
    p.add_argument("--max-steps", type=int, default=1000, help="step cap per ladder run (default 1000)")
    p.add_argument("--at", type=float, default=0.0, metavar="SECONDS",
                   help="predict at the state the implicit integrator reaches after SECONDS (default 0: "
                   "the initial state)")
    p.add_argument("--predict-only", action="store_true", help="print the predictions, run no ladder")


def cmd_stability(args):
    from massspring import stability
    from massspring.scene import load_scene

    for name in ("run_duration", "at"):
        value = getattr(args, name)
        if not (value >= 0 if name == "at" else value > 0):
            raise UsageError(f"--{name.replace('_', '-')}: must be {'>= 0' if name == 'at' else '> 0'}, got {value}")
    if args.max_steps < 1:
        raise UsageError(f"--max-steps: must be >= 1, got {args.max_steps}")
    if args.integrator or args.dt is not None or args.no_definiteness_fix:
        raise UsageError("--integrator/--dt/--no-definiteness-fix: the ladder runs every integrator "
                         "at its own dts, implicit with the fix on and off")
    scene = load_scene(args.scene).with_settings(args.set)
    prefix = Path(args.out) if args.out else Path(f"stability-{scene.name}")
    if not prefix.parent.is_dir():
        raise UsageError(f"--out: directory {str(prefix.parent)!r} does not exist")
    options = dict(precision=args.precision, cg_tol=args.cg_tol, cg_max_iter=args.cg_max_iter)
    model, positions = scene.model(), None
    if args.at > 0:
        settle = scene.simulation("implicit", **options)
        settle.step(max(1, int(round(args.at / settle.dt))))
        positions = settle.positions
    prediction = stability.predict(model, positions)
    print("\n".join(stability.prediction_lines(prediction, scene.name)))
    if args.predict_only:
        return EXIT_OK
    print(f"ladder: each run min({args.run_duration:g} s, {args.max_steps} steps); implicit with the "
          "definiteness fix on and off; the scene's default dt last in each group")
    rows = stability.ladder(scene, prediction, duration=args.run_duration, max_steps=args.max_steps,
                            progress=lambda row: print(".", end="", file=sys.stderr, flush=True), **options)
    print(file=sys.stderr)
    print(stability.format_table(rows))
    written = stability.write_outputs(rows, prediction, scene.name, prefix)
    try:
        written.append(stability.plot(rows, f"{prefix}.png", f"{scene.name}: stability ladder"))
    except ImportError:
        print("plot skipped: matplotlib is not installed (pip install 'massspring[plot]')")
    print("wrote " + ", ".join(str(p) for p in written))
    return EXIT_OK


COMMANDS = {"run": cmd_run, "scenes": cmd_scenes, "info": cmd_info, "study": cmd_study,
            "stability": cmd_stability}


def main(argv=None):
    args = build_parser().parse_args(argv)
    try:
        return COMMANDS[args.command](args)
    except ValueError as exc:  # SceneError, UsageError and Model/Simulation validation
        print(f"massspring: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except BrokenPipeError:  # output piped into e.g. `head`
        sys.stderr.close()
        return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
