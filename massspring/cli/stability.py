"""``massspring stability``: the predicted dt limits and a ladder of runs around them."""

from __future__ import annotations

import math
import sys
from pathlib import Path

from massspring.support import progress
from massspring.support.defaults import MAX_STEPS
from massspring.support.extras import install_hint
from massspring.integrators import DEFAULT
from massspring.support.text import format_seconds
from massspring.cli.common import EXIT_DIVERGED, EXIT_OK, UsageError, add_cluster_arguments, add_scene_arguments, solver_options


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
    from massspring.support.errors import DivergenceError
    from massspring.engine.simulation import run

    for name in ("run_duration", "at"):
        value = getattr(args, name)
        ok = math.isfinite(value) and (value >= 0 if name == "at" else value > 0)
        if not ok:
            raise UsageError(f"--{name.replace('_', '-')}: must be a finite number "
                             f"{'>= 0' if name == 'at' else '> 0'}, got {value}")
    if not 1 <= args.max_steps <= MAX_STEPS:
        raise UsageError(f"--max-steps: must be within 1..{MAX_STEPS}, got {args.max_steps}")
    if args.integrator or args.dt is not None or args.definiteness_fix is not None:
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
        settle = scene.simulation(DEFAULT, tol=None, **options)  # in steps: fixed ones
        steps = args.at / settle.dt
        if not steps <= MAX_STEPS:
            raise UsageError(f"--at: {args.at:g} s at the {DEFAULT} dt {format_seconds(settle.dt)} is {steps:.3g} steps, "
                             f"more than {MAX_STEPS:.3g}")
        steps = max(1, round(steps))
        label = f"stability {scene.name}: settling for --at {args.at:g} s ({DEFAULT}, dt {format_seconds(settle.dt)})"
        try:
            with progress.steps(label, steps, settle.dt, show=steps > 1) as on_progress:
                run(settle, steps, progress=on_progress)
        except DivergenceError as exc:
            print(f"massspring: stability {scene.name}: --at {args.at:g} s: the settling run: {exc}", file=sys.stderr)
            return EXIT_DIVERGED
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
        print(f"plot skipped: matplotlib is not installed ({install_hint('plot')})")
    print("wrote " + ", ".join(str(p) for p in written))
    return EXIT_OK
