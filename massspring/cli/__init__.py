"""The massspring command line: run built-in or user scenes, list them, describe them.

It parses, calls and prints: the physics is in ``Simulation`` and the run loop in
``simulation.run``. Exit codes: 0 success; 2 bad usage or bad input (one line on
stderr, no traceback), decided before the first step; 3 the simulation diverged
(the last good state is still summarised and written); 1 an output could not be
written after the run; 130 interrupted by Ctrl-C, 143 by SIGTERM (the state reached
so far is still summarised and written).

One module per verb (``run``, ``scenes`` (with ``info``), ``study``, ``stability``,
``sweep``, ``fit``: its arguments and its command), ``pictures`` (the GIF, PNG and frame
export options of ``run``) and ``common`` (what several verbs share); here the parser
and ``main``.
"""

from __future__ import annotations

import argparse
import signal
import warnings
import sys

from massspring.analysis.cluster import ClusterError
from massspring.support.errors import KinkWarning
from massspring.cli.common import (EXIT_DIVERGED, EXIT_INTERRUPTED, EXIT_OK, EXIT_OUTPUT, EXIT_USAGE, Terminated,
                                   UsageError, add_scene_arguments, add_tolerance_arguments,
                                   main_thread)
from massspring.cli.pictures import add_export_arguments, add_frame_arguments
from massspring.cli.run import cmd_run
from massspring.cli.scenes import cmd_info, cmd_scenes
from massspring.cli.stability import add_stability_arguments, cmd_stability
from massspring.cli.fit import add_fit_arguments, cmd_fit
from massspring.cli.study import add_study_arguments, cmd_study
from massspring.cli.sweep import add_sweep_arguments, cmd_sweep
from massspring.support.text import clipped

__all__ = ["EXIT_DIVERGED", "EXIT_INTERRUPTED", "EXIT_OK", "EXIT_OUTPUT", "EXIT_USAGE", "Terminated", "UsageError",
           "build_parser", "main"]


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
    add_tolerance_arguments(run)
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
    add_tolerance_arguments(info)

    stab = verbs["stability"] = sub.add_parser(
        "stability", help="predict each integrator's dt limit from the spectrum, then run a ladder of dt around it")
    add_stability_arguments(stab, INTEGRATORS)

    study = verbs["study"] = sub.add_parser(
        "study", help="work-precision study: error against run time per integrator and dt")
    add_study_arguments(study)

    sweep = verbs["sweep"] = sub.add_parser(
        "sweep", help="run a scene once per combination of varied parameters, here or on a Dask cluster")
    add_sweep_arguments(sweep, INTEGRATORS)

    fit = verbs["fit"] = sub.add_parser(
        "fit", help="fit a scene's stiffness, damping, ... to recorded frames (gradients through every step)")
    add_fit_arguments(fit)
    return parser, verbs


COMMANDS = {"run": cmd_run, "scenes": cmd_scenes, "info": cmd_info, "study": cmd_study,
            "stability": cmd_stability, "sweep": cmd_sweep, "fit": cmd_fit}


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


def _one_line(show):
    """``warnings.showwarning`` that prints a ``KinkWarning`` as "massspring: warning: ..."
    (no file and line of the library) and hands others to ``show``."""
    def showwarning(message, category, filename, lineno, file=None, line=None):
        if issubclass(category, KinkWarning):
            print(f"massspring: warning: {message}", file=sys.stderr)
        else:
            show(message, category, filename, lineno, file, line)
    return showwarning


def main(argv=None):
    parser, verbs = build_parser()
    args, unknown = parser.parse_known_args(joined_values(sys.argv[1:] if argv is None else argv))
    if unknown:  # a misspelt option after a verb: that verb's usage, not the top-level one
        verbs[args.command].error(f"unrecognized arguments: {' '.join(unknown)}")
    previous = signal.signal(signal.SIGTERM, _terminate) if main_thread() else None
    try:
        with warnings.catch_warnings():  # massspring's own warnings: one line each, once
            warnings.simplefilter("once", KinkWarning)
            warnings.showwarning = _one_line(warnings.showwarning)
            return COMMANDS[args.command](args)
    except ValueError as exc:  # SceneError, UsageError and Model/Simulation validation
        print(f"massspring: error: {clipped(str(exc))}", file=sys.stderr)
        return EXIT_USAGE
    except ClusterError as exc:  # no worker, or the scheduler gone, while tasks wait
        print(f"massspring: error: --workers/--address: {clipped(str(exc))}", file=sys.stderr)
        return EXIT_USAGE
    except Terminated as exc:  # SIGTERM outside a run (e.g. while loading)
        return 128 + exc.signum
    except KeyboardInterrupt:  # Ctrl-C outside a run (a run reports its own)
        print("massspring: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except BrokenPipeError:  # output piped into e.g. `head`
        sys.stderr.close()
        return EXIT_OK
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
