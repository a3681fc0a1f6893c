"""What several verbs share: exit codes, errors, the scene and solver options, and building a Simulation from them."""

from __future__ import annotations


from massspring.support import progress
from massspring.support import validate
from massspring.support.defaults import PRECISIONS
from massspring.support.extras import install_hint


EXIT_OK, EXIT_OUTPUT, EXIT_USAGE, EXIT_DIVERGED, EXIT_INTERRUPTED = 0, 1, 2, 3, 130


class UsageError(ValueError):
    """Bad command-line input; reported in one line with exit code 2."""


class Terminated(KeyboardInterrupt):
    """SIGTERM (timeout, container stop, batch scheduler): handled like Ctrl-C."""

    def __init__(self, signum):
        super().__init__(signum)
        self.signum = signum


def add_scene_arguments(p, integrators):
    from massspring.device import ARCHS
    from massspring.integrators import OPTIONS

    p.add_argument("scene", help="a built-in scene name (see `massspring scenes`), a TOML file or an OBJ mesh (run with "
                   "the defaults of docs/scenes.md, 'Your own mesh')")
    p.add_argument("--integrator", choices=tuple(integrators), help="time integrator (default: the scene's)")
    p.add_argument("--dt", type=float, help="time step in s (default: the scene's for the integrator)")
    p.add_argument("--precision", choices=PRECISIONS, default=PRECISIONS[0])
    p.add_argument("--arch", default="cpu", help=f"Taichi arch: {', '.join(ARCHS)} (default cpu); another "
                   "than the CPU is tried before the run and refused if this machine lacks it")
    for option in OPTIONS.values():
        add_option_flag(p, option)
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a scene model parameter, e.g. --set resolution=64, "
                   "--set gravity=[0,0,-1.62] or --set drag=0.005 (TOML values; repeatable)")


def add_tolerance_arguments(p, frozen=False):
    """--tol, --min-dt, --max-dt: an error-controlled run (``Simulation(tol=...)``);
    ``frozen``: a fit's, whose gradient is that of the chosen steps frozen."""
    if frozen:
        p.add_argument("--tol", type=float, help="error-controlled steps: each run's steps are chosen by an "
                       "error-controlled run (the error wanted at the end, as `massspring run --tol` takes it) landing "
                       "on the recorded frames, and its gradient is that of those steps frozen; --newton-tol and "
                       "--cg-tol then solve the frozen run (default: steps of the recording's dt)")
    else:
        p.add_argument("--tol", type=float, help="error-controlled steps: the error wanted at the end of the run "
                       "(RMS position error of the moving particles over the scene's size, as `massspring study` "
                       "reports it); the run picks each step from an estimate of its error, --dt is then the first "
                       "step, and Newton's and CG's tolerances follow (default: the scene's tol, else fixed steps of "
                       "--dt)")
    p.add_argument("--min-dt", type=float, help="with --tol: the smallest step in s (default 1e-9 x the duration); "
                   "a run whose step would fall below it stops with exit 3")
    p.add_argument("--max-dt", type=float, help="with --tol: the largest step in s (default the duration; explicit, "
                   "symplectic, rk4: the dt they suggest, half the predicted stability limit; implicit: a frame, "
                   "1/60 s)")


def tolerance_options(args, frozen=False):
    """The Simulation arguments of --tol, --min-dt, --max-dt (those given), checked: a
    UsageError naming the flag (``frozen``: a fit's, which takes --newton-tol, --cg-tol too)."""
    from massspring.engine.adaptive import Tolerance

    given = {name: getattr(args, name, None) for name in ("tol", "min_dt", "max_dt")}
    given = {name: value for name, value in given.items() if value is not None}
    if not given:
        return {}
    if "tol" not in given:
        raise UsageError(f"--{next(iter(given)).replace('_', '-')}: only with --tol (an error-controlled run)")
    try:
        Tolerance.of(given["tol"], given.get("min_dt"), given.get("max_dt"), 1.0 if "max_dt" in given else None)
    except ValueError as exc:
        raise UsageError("--" + str(exc).replace("_", "-", 1)) from None
    for name in () if frozen else ("newton_tol", "cg_tol"):
        if getattr(args, name, None) is not None:
            raise UsageError(f"--{name.replace('_', '-')}: an error-controlled run (--tol) derives it from --tol; "
                             f"give one or the other")
    return given


def add_option_flag(p, option):
    """The flag of a solver option (``integrators.options.Option``): --cg-tol, --no-definiteness-fix."""
    from massspring.integrators import takers

    help = f"{', '.join(takers(option.name))}: {option.doc}"
    if option.kind == "switch":
        p.add_argument(option.flag, dest=option.name, action="store_const", const=not option.default,
                       help=f"{help} ({'off' if option.default else 'on'}; default: the scene's [solver], else "
                       f"{'on' if option.default else 'off'})")
        return
    p.add_argument(option.flag, dest=option.name, type=option.type, choices=option.choices or None,
                   help=f"{help} (default: the scene's [solver], else {option.described_default()})")


def make_simulation(args):
    """Scene + options -> (scene, Simulation); raises ValueError on bad input before any kernel runs."""
    from massspring.device import ensure_taichi
    from massspring.scene import load_scene

    scene = load_scene(args.scene).with_settings(args.set)
    options = solver_options(args)
    try:
        if args.dt is not None:
            validate.positive_float("--dt", args.dt)
        ensure_taichi(args.arch, "--arch")
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    check_taken(args.integrator or scene.integrator, options)
    options.update(tolerance_options(args))
    if any(getattr(args, name, None) is not None for name in ("steps", "every")):
        options.setdefault("tol", None)  # counting steps asks for fixed ones, as --dt does: the scene's tol gives way
    with progress.phase(f"{args.command} {scene.name}: building the model and the simulation",
                        show=not getattr(args, "quiet", False)):
        sim = scene.simulation(integrator=args.integrator, dt=args.dt, precision=args.precision, arch=args.arch,
                               **options)
    return scene, sim


def check_taken(integrator, options):
    """A UsageError naming the flags of ``options`` that ``integrator`` does not take."""
    from massspring.integrators import OPTIONS, takers, untaken

    for lacks, names in untaken(integrator, options).items():
        raise UsageError(f"{'/'.join(OPTIONS[n].flag for n in names)}: {integrator} {lacks}; "
                         f"{'these options are' if len(names) > 1 else 'this option is'} for "
                         + ", ".join(takers(names[0])))


def solver_options(args):
    """The solver options given on the command line (``integrators.OPTIONS``), checked
    (UsageError naming the flag); the scene's [solver] table (``Scene.simulation``)
    supplies the others."""
    from massspring.integrators import OPTIONS

    options = {}
    for name, option in OPTIONS.items():
        value = getattr(args, name, None)
        if value is None:
            continue
        try:
            options[name] = option.check(value, option.flag)
        except ValueError as exc:
            raise UsageError(str(exc)) from None
    return options


def integrator_names():
    from massspring.integrators import INTEGRATORS

    return tuple(INTEGRATORS)


def add_cluster_arguments(p):
    where = p.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, metavar="N", help="run the cases on a local Dask cluster of N "
                       f"worker processes, started for this command ({install_hint('cluster')})")
    where.add_argument("--address", metavar="tcp://HOST:PORT",
                       help="run the cases on the Dask cluster whose scheduler listens there")


def needs_matplotlib(option):
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        raise ValueError(f"{option}: matplotlib is not installed ({install_hint('plot')})") from None


def main_thread():
    import threading

    return threading.current_thread() is threading.main_thread()
