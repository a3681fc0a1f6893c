"""``massspring fit``: a scene's parameters fitted to recorded frames by gradients through every step."""

from __future__ import annotations

import sys
from contextlib import contextmanager

from massspring.cli.common import (EXIT_DIVERGED, EXIT_OK, UsageError, add_option_flag, add_tolerance_arguments,
                                   check_taken, solver_options, tolerance_options)


# massspring.gradient's arguments -> the options of `massspring fit` that give them
FIT_OPTIONS = {"wrt": "--params", "integrator": "--integrator", "model": "scene", "dts": "--tol", "tol": "--tol",
               "min_dt": "--min-dt", "max_dt": "--max-dt"}


def add_fit_arguments(p):
    from massspring.analysis.parameter_fit import FACTOR_RANGE, FITTABLE, MAX_ITER
    from massspring.gradients import differentiable
    from massspring.integrators import OPTIONS

    p.add_argument("scene", help="a built-in scene name (see `massspring scenes`), a TOML file or an OBJ mesh (run with "
                   "the defaults of docs/scenes.md, 'Your own mesh')")
    p.add_argument("--frames", required=True, metavar="DIR",
                   help="the recording: a folder written by `massspring run SCENE --export DIR --format npz` "
                   "(the fit starts from its first frame and steps with its dt)")
    p.add_argument("--params", required=True, metavar="NAMES",
                   help=f"comma-separated parameters to fit, each scaled by one factor: {', '.join(FITTABLE)}")
    p.add_argument("--integrator", choices=differentiable(),
                   help="time integrator of the fitted runs (default: the scene's)")
    for option in OPTIONS.values():
        add_option_flag(p, option)
    add_tolerance_arguments(p, frozen=True)
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a scene model parameter (repeatable), as `massspring run` takes it")
    p.add_argument("--start", type=float, default=1.0,
                   help=f"every factor's first value, within {FACTOR_RANGE[0]:g}..{FACTOR_RANGE[1]:g} (default 1: "
                   "the scene's values)")
    p.add_argument("--max-iter", type=int, default=MAX_ITER,
                   help=f"L-BFGS-B iterations at most, each one run and its gradient or more (default {MAX_ITER})")
    p.add_argument("--out", metavar="FILE", help="also write the result as JSON to FILE")
    p.add_argument("--quiet", action="store_true", help="no line per iteration")


@contextmanager
def named_options():
    """A ValueError of ``massspring.gradient``'s argument checks as a UsageError naming the option."""
    try:
        yield
    except ValueError as exc:
        name, _, reason = str(exc).partition(": ")
        if name in FIT_OPTIONS:
            raise UsageError(f"{FIT_OPTIONS[name]}: {reason}") from None
        raise


def cmd_fit(args):
    from massspring.support import validate
    from massspring.analysis import parameter_fit
    from massspring.support.errors import DivergenceError, GradientError
    from massspring.io.files import check_writable, write_json
    from massspring.scene import load_scene

    try:
        params = parameter_fit.check_params(name.strip() for name in args.params.split(",") if name.strip())
    except ValueError as exc:
        raise UsageError(f"--{exc}") from None
    try:
        validate.count("--max-iter", args.max_iter, low=1)
        low, high = parameter_fit.FACTOR_RANGE
        if not low <= validate.positive_float("--start", args.start) <= high:
            raise ValueError(f"--start: must be within {low:g}..{high:g}, got {args.start!r}")
        if args.out is not None:  # as `run` checks its outputs: before the fit, not after it
            check_writable(args.out, "--out")
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    options = solver_options(args)
    tolerance = tolerance_options(args, frozen=True)
    scene = load_scene(args.scene).with_settings(args.set)
    integrator = args.integrator or scene.integrator
    check_taken(integrator, options)
    model = scene.model()
    with named_options():
        parameter_fit.check_fit(model, params, integrator)
    recording = parameter_fit.read_recording(args.frames, model)

    def show(iteration, factors, rms):
        text = ", ".join(f"{name} x{value:.8g}" for name, value in factors.items())
        print(f"iteration {iteration}: {text}; rms distance {rms:.4g} m", file=sys.stderr, flush=True)

    steps = f"tol {tolerance['tol']:g}" if tolerance else f"dt {recording.dt:g} s"
    print(f"fit {scene.name}: {', '.join(params)} ({integrator}, {steps}, {len(recording.steps)} "
          f"frames over {int(recording.steps[-1])} steps from {args.frames})", flush=True)
    try:
        with named_options():
            result = parameter_fit.fit_parameters(model, recording, params, integrator=integrator, start=args.start,
                                                  max_iter=args.max_iter, progress=None if args.quiet else show,
                                                  **tolerance, **options)
    except DivergenceError as exc:
        print(f"massspring: a run of the fit diverged: {exc}; try a --start nearer the truth or a smaller "
              "recorded dt", file=sys.stderr)
        return EXIT_DIVERGED
    except GradientError as exc:
        raise UsageError(f"fit: {exc}") from None
    for name in params:
        print(f"{name:13s} x{result['factors'][name]:.8g}  (mean {result['values'][name]:.8g})")
    print(f"rms distance {result['rms_m']:.4g} m after {result['iterations']} L-BFGS-B iterations "
          f"({result['evaluations']} runs with their gradient); {result['message']}")
    if args.out:
        write_json(args.out, {"scene": scene.name, "integrator": integrator, "frames": str(args.frames),
                              "dt": recording.dt, "tol": tolerance.get("tol"), **result})
        print(f"wrote {args.out}")
    return EXIT_OK
