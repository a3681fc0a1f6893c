"""``run``'s pictures and frame export: their options, planning them before the run, writing them after."""

from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass, replace

import numpy as np

from massspring.support.text import format_seconds
from massspring.support.extras import install_hint
from massspring.cli.common import Terminated, UsageError


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
    formats = "; ".join(f"{f.name}: {f.help}" + (f" (needs {f.module}: {install_hint(f.extra)})"
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


def plan_frames(args, sim, steps, seconds=None):
    """The steps of this run (0..steps) at which --gif/--png record and --export writes a
    frame (``render.frame_steps``); None without any of them. An error-controlled run's
    (``seconds``: its duration) are slots of ``steps`` over its duration, which it lands on."""
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
    if seconds is not None and args.every is not None:
        raise UsageError("--every: counts steps, which an error-controlled run (--tol) picks itself; give --frames "
                         "or --fps")
    try:
        return render.frame_steps(steps, frames=args.frames, every=args.every,
                                  duration=steps * sim.dt if seconds is None else seconds, fps=fps)
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


def finish_export(export, sim, reached, diverged, stopped):
    """Mark the manifest with how the run ended and say what was written (on stderr if
    the run stopped early, at ``reached``, or a file failed). Returns ["--export"] if a
    file failed."""
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
        print(f"massspring: the run stopped at {reached}; wrote {where}, the frames up to then", file=sys.stderr)
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


def finish_pictures(plan, scene, sim, reached=None, stop=None):
    """Render what was recorded, write the GIF/PNG and say what was written (on stderr
    if the run stopped early, at ``reached``, or the rendering did). Returns the options
    whose file failed."""
    from massspring.io import render

    rec = plan.recording
    if not len(rec):
        print("massspring: no frame was recorded: nothing written to " +
              " or ".join(p for p in (plan.gif, plan.png) if p), file=sys.stderr)
        return []
    start = time.perf_counter()
    renderer = render.FrameRenderer(sim.model, np.stack(rec.positions), plan.view, plan.size,
                                    label=f"{scene.name}  {sim.integrator}  " + (
                                        f"dt = {format_seconds(sim.dt)}" if sim.tol is None else f"tol {sim.tol:g}"),
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
    elif reached is not None:
        print(f"massspring: the run stopped at {reached}; wrote the frames recorded up to then: {note}",
              file=sys.stderr)
    else:
        print(f"pictures    wrote {note}")
    return list(result.errors)
