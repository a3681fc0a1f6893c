"""``massspring study``: error against run time of integrators on a scene."""

from __future__ import annotations

from pathlib import Path

from massspring.cli.common import EXIT_OK, UsageError, add_cluster_arguments
from massspring.cli.pictures import _number
from massspring.support.extras import install_hint


def add_study_arguments(p):
    from massspring.integrators import STUDIED

    p.add_argument("scene", help="a built-in scene name (see `massspring scenes`), a TOML file or an OBJ mesh (run with "
                   "the defaults of docs/scenes.md, 'Your own mesh')")
    p.add_argument("--out", help="output directory (default: a new ./study-SCENE)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a scene model parameter (repeatable)")
    p.add_argument("--duration", type=float, help="simulated end time in s (default: a tenth of the scene's)")
    p.add_argument("--integrators", default=",".join(STUDIED), help="comma-separated list (default %(default)s)")
    p.add_argument("--rungs", type=int, default=7, help="dt values per line, a factor of 2 apart (default 7)")
    p.add_argument("--cg-tols", default="1e-2,1e-4,1e-6", help="implicit: comma-separated CG tolerances")
    p.add_argument("--newton-tols", default="1e-3,1e-6", help="backward-euler, bdf2: comma-separated Newton "
                   "tolerances")
    p.add_argument("--preconditioners", default="auto",
                   help="implicit, backward-euler, bdf2, midpoint: comma-separated preconditioners, a line each "
                   "(auto, block-jacobi, multigrid, multigrid-f32, none; default auto: what each integrator's own "
                   "run picks)")
    p.add_argument("--tol", default="", help="error-controlled lines: comma-separated tolerances, a run each per "
                   "integrator with its steps chosen for that error (`run --tol`), beside the dt ladders "
                   "(default none)")
    p.add_argument("--repeats", type=int, default=3, help="timed runs per configuration, at most (default 3)")
    p.add_argument("--cache-dir", help="RK4 reference cache (default $MASSSPRING_CACHE, "
                   "else $XDG_CACHE_HOME/massspring or ~/.cache/massspring)")
    add_cluster_arguments(p)


# run_study's arguments -> the options of `massspring study` that give them
STUDY_OPTIONS = {"integrators": "--integrators", "duration": "--duration", "rungs": "--rungs",
                 "cg_tols": "--cg-tols", "newton_tols": "--newton-tols", "preconditioners": "--preconditioners",
                 "repeats": "--repeats", "tol": "--tol"}


def cmd_study(args):
    from massspring.analysis import cluster, report, study
    from massspring.scene import load_scene

    scene = load_scene(args.scene).with_settings(args.set)
    out = Path(args.out) if args.out else report.new_out_dir(scene.name)
    if out.exists() and not out.is_dir():
        raise UsageError(f"--out: {str(out)!r} exists and is not a directory")
    tols = {}
    for key, flag, given in (("cg_tols", "--cg-tols", args.cg_tols), ("newton_tols", "--newton-tols", args.newton_tols),
                             ("tols", "--tol", args.tol)):
        try:
            tols[key] = [_number(text) for text in filter(str.strip, given.split(","))]
        except ValueError as exc:
            raise UsageError(f"{flag}: {exc}") from None
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
        print(f"plot skipped: matplotlib is not installed ({install_hint('plot')})")
    print("wrote " + ", ".join(str(p) for p in written))
    return EXIT_OK
