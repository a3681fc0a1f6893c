"""The ``massspring`` command line: run built-in or user scenes, list them, describe them.

Exit codes: 0 success; 2 bad usage or bad scene/input (one line on stderr, no
traceback); 130 interrupted (the state reached so far is still written).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

EXIT_OK, EXIT_USAGE, EXIT_INTERRUPTED = 0, 2, 130


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

    sub.add_parser("scenes", help="list the built-in scenes")

    info = sub.add_parser("info", help="show a scene's size, defaults, and what a run compiles")
    add_scene_arguments(info)
    return parser


def add_scene_arguments(p):
    p.add_argument("scene", help="a built-in scene name (see `massspring scenes`) or a TOML file")
    p.add_argument("--integrator", choices=("explicit", "symplectic", "implicit"),
                   help="time integrator (default: the scene's)")
    p.add_argument("--dt", type=float, help="time step in s (default: the scene's for the integrator)")
    p.add_argument("--precision", choices=("f64", "f32"), default="f64")
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
                           definiteness_fix=not args.no_definiteness_fix)
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
    print(f"dt defaults " + ", ".join(f"{k} {v:g}" for k, v in scene.dt.items()))
    print(f"terms       {', '.join(info['terms'])}")
    print(f"arrays      {', '.join(info['arrays'])} ({info['bytes'] / 1e6:.2f} MB)")
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

    energy0 = sim.energy()
    start = time.perf_counter()
    interrupted = False
    try:
        advance(sim, steps, show=not args.quiet and steps > 1)
    except KeyboardInterrupt:
        interrupted = True
    wall = time.perf_counter() - start
    if args.out:
        write_state(sim, args.out)
    print_summary(scene, sim, wall, energy0, args.out)
    if interrupted:
        print(f"massspring: interrupted after {sim.steps} of {steps} steps; "
              f"the state reached so far{' was written' if args.out else ' is above'}", file=sys.stderr)
        return EXIT_INTERRUPTED
    return EXIT_OK


def advance(sim, steps, show=True):
    """Step ``sim`` by ``steps`` in chunks, with a progress bar on stderr when ``show``."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    chunk = max(1, steps // 200)
    with Progress(TextColumn("[progress.description]{task.description}"), BarColumn(),
                  TextColumn("{task.completed}/{task.total} steps"), TimeElapsedColumn(),
                  TimeRemainingColumn(), transient=True, disable=not show) as bar:
        task = bar.add_task(f"{sim.integrator} dt={sim.dt:g}", total=steps)
        done = 0
        while done < steps:
            k = min(chunk, steps - done)
            sim.step(k)
            done += k
            bar.update(task, completed=done)


def write_state(sim, path):
    """Write positions, velocities, springs and time to ``path`` (.npz) atomically."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp.npz", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            np.savez(fh, positions=sim.positions, velocities=sim.velocities,
                     springs=sim.model.springs, time=sim.time, steps=sim.steps, dt=sim.dt)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


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
    print(f"energy      start {energy0['total']:.6g} J, end {energy1['total']:.6g} J "
          f"(kinetic {energy1['kinetic']:.4g}, spring {energy1['spring']:.4g}, gravity {energy1['gravity']:.4g})")
    print(f"compiled    terms: {', '.join(info['terms'])}; arrays: {', '.join(info['arrays'])}")
    if out:
        print(f"wrote       {out}")


COMMANDS = {"run": cmd_run, "scenes": cmd_scenes, "info": cmd_info}


def main(argv=None):
    args = build_parser().parse_args(argv)
    try:
        return COMMANDS[args.command](args)
    except ValueError as exc:  # SceneError, UsageError and Model/Simulation validation
        print(f"massspring: error: {exc}", file=sys.stderr)
        return EXIT_USAGE


if __name__ == "__main__":
    sys.exit(main())
