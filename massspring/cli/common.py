"""What several verbs share: exit codes, errors, the scene and solver options, and building a Simulation from them."""

from __future__ import annotations


from massspring import progress, validate
from massspring.defaults import PRECISIONS


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


def integrator_names():
    from massspring.integrators import INTEGRATORS

    return tuple(INTEGRATORS)


def add_cluster_arguments(p):
    where = p.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, metavar="N", help="run the cases on a local Dask cluster of N "
                       "worker processes, started for this command (pip install 'massspring[cluster]')")
    where.add_argument("--address", metavar="tcp://HOST:PORT",
                       help="run the cases on the Dask cluster whose scheduler listens there")


def needs_matplotlib(option):
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        raise ValueError(f"{option}: matplotlib is not installed (pip install 'massspring[plot]')") from None


def main_thread():
    import threading

    return threading.current_thread() is threading.main_thread()
