"""``massspring sweep``: a scene run over a grid of parameter values, to a CSV."""

from __future__ import annotations

import sys
from pathlib import Path

from massspring.support import validate
from massspring.support.defaults import MAX_STEPS
from massspring.support.extras import install_hint
from massspring.cli.common import (
    EXIT_INTERRUPTED, EXIT_OK, Terminated, UsageError, needs_matplotlib, add_cluster_arguments, add_scene_arguments,
    add_tolerance_arguments, solver_options, tolerance_options)


def add_sweep_arguments(p, integrators):
    from massspring.analysis.sweep import MAX_CASES, METRICS

    add_scene_arguments(p, integrators)
    p.add_argument("--vary", action="append", default=[], metavar="KEY=V1,V2,...", required=True,
                   help="a model parameter (as --set), dt, integrator, preconditioner or tol and its values; "
                   "repeatable: one case per combination")
    length = p.add_mutually_exclusive_group()
    length.add_argument("--steps", type=int, help="steps per case (default: the scene's duration / dt)")
    length.add_argument("--duration", type=float, help="simulated seconds per case (default: the scene's)")
    p.add_argument("--out", required=True, help="the CSV: a row per case, appended as each finishes; "
                   "an existing one of the same sweep is resumed (its finished cases are skipped)")
    p.add_argument("--states", metavar="DIR", help="keep each case's final state as DIR/caseNNNN.npz")
    p.add_argument("--plot", metavar="PNG", help="draw --metric against the first varied key (a line per "
                   f"value of the second) ({install_hint('plot')})")
    p.add_argument("--metric", choices=METRICS, default="energy", help="what --plot draws (default energy)")
    p.add_argument("--yes", action="store_true", help=f"run more than {MAX_CASES} cases")
    p.add_argument("--quiet", action="store_true", help="no line per finished case")
    add_tolerance_arguments(p)
    add_cluster_arguments(p)


def cmd_sweep(args):
    from massspring.analysis import cluster, sweep
    from massspring.device import ensure_taichi
    from massspring.io.files import check_writable
    from massspring.scene import load_scene

    scene = load_scene(args.scene).with_settings(args.set)
    tolerance = tolerance_options(args)
    try:
        vary = sweep.parse_vary(args.vary)
        if (tolerance or "tol" in vary) and args.steps is not None:
            raise ValueError("--steps: an error-controlled sweep (--tol) is measured in time; give --duration")
        cases = sweep.plan(scene, vary, integrator=args.integrator, confirm=args.yes, option="--vary")
        for name in ("dt", "duration"):
            if getattr(args, name) is not None:
                validate.positive_float(f"--{name}", getattr(args, name))
        if args.duration is not None and not (tolerance or "tol" in vary):
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
            needs_matplotlib("--plot")
        cluster.check_options(args.workers, args.address)
        ensure_taichi(args.arch, "--arch")
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    options = dict(precision=args.precision, arch=args.arch, **solver_options(args), **tolerance)
    setup = sweep.setup_text(scene, args.integrator, args.dt, args.duration, args.steps, options)
    try:
        before = sweep.resumable(args.out, list(vary), cases, setup)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    total = len(cases)
    finished = []

    def on_case(case, row):
        finished.append(row)
        if not args.quiet:
            message = f": {row['message']}" if row["message"] else ""
            took = f" in {row['wall_s']:.2f} s" if isinstance(row["wall_s"], float) else ""  # a lost worker's: none
            print(f"sweep {scene.name}: case {case.number} of {total} ({case.label()}): {row['status']}{took}"
                  f"{message}", file=sys.stderr, flush=True)

    if not args.quiet and before:
        print(f"sweep {scene.name}: resuming {args.out}: its {before} finished case(s) of {total} are skipped",
              file=sys.stderr)
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
    except (ValueError, cluster.ClusterError) as exc:  # the CSV or a state that cannot be written, a lost cluster
        kept = f" ({len(finished)} new case(s) finished; {args.out} holds every finished one)" if finished else ""
        where = "--workers/--address: " if isinstance(exc, cluster.ClusterError) else ""
        raise UsageError(f"{where}{exc}{kept}") from None
    print(sweep.format_table(rows, list(vary)))
    written = [args.out]
    if args.plot is not None:
        written.append(sweep.plot(rows, list(vary), args.metric, args.plot, f"{scene.name}: {args.metric}"))
    print("wrote " + ", ".join(str(p) for p in written))
    return EXIT_OK
