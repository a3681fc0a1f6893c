"""Train DiffTaichi's mass-spring robot from DiffTaichi's own source, GUI removed, and time it.

DiffTaichi (Hu et al., ICLR 2020, https://github.com/taichi-dev/difftaichi) is not
part of this project (its repository has no license file, so none of its code is
copied here). This script takes the ``examples/`` folder of a checkout the user
already has (holding ``mass_spring.py`` and ``mass_spring_robot_config.py``) and runs
``mass_spring.py`` unmodified, as ``mass_spring.py ROBOT train --iters N``, in a child
``sys.executable`` process started with a small shim (``SHIM`` below, passed with
``-c``) that, before the file runs:

* replaces ``taichi.GUI`` by ``NoGUI``, an object whose methods (line, circle,
  circles, show, ...) accept anything and do nothing, so no window opens and no
  frame is written (the arguments are still computed, as in the original: the
  field reads for drawing stay part of the timed work);
* wraps ``builtins.print`` to stamp ``time.perf_counter()`` (wall) and
  ``time.process_time()`` (CPU time of the whole process, all threads) when
  ``setup_robot`` prints ``n_objects=`` (just before ``optimize``) and when each
  ``Iter= i Loss= value`` line is printed, recording the loss from the arguments;
* with ``--threads N``, wraps ``taichi.init`` to add ``arch=ti.cpu`` and
  ``cpu_max_num_threads=N`` to the arguments ``mass_spring.py`` gives it;
* then ``runpy.run_path(mass_spring.py, run_name='__main__')``, whose returned module
  globals give ``steps``, ``dt``, ``head_id`` and the field ``x``.

The child runs in a temporary working directory (``mass_spring.py``'s final
``forward('final<id>')`` creates ``mass_spring/final<id>/`` there), deleted
afterwards; its output (Taichi's banner, the ``Iter=`` lines, the gradient norms)
goes to this process's stdout/stderr. Nothing is fetched from the network.

Per iteration i (0-based, as printed by ``mass_spring.py``):

* ``loss``: the printed loss, ``-x[steps - 1, head_id][0]`` (minus the head's x
  position at the last step of that iteration's forward pass, before the
  iteration's gradient step);
* ``wall_s`` / ``cpu_s`` (seconds): wall / process CPU time from the previous
  ``Iter=`` line to this one, i.e. one whole training cycle: the previous
  iteration's gradient step (Python-scope field loops), ``clear()``, forward and
  backward pass under ``ti.ad.Tape``. For iteration 0 it runs from the
  ``n_objects=`` line instead, so it includes the weight initialisation and the
  compilation of every kernel (less with Taichi's offline cache warm); the
  summary medians therefore use iterations 1.. only (none when ``--iters 1``).
  Iteration 1 can still be slower than the rest: its window holds the first
  gradient step, whose Python-scope reads and writes of the weight fields and
  their ``.grad`` fields are the first ones (Taichi compiles accessors for them).
  The last iteration's gradient step falls after the last stamp and is not timed.

Positions are in DiffTaichi's simulation units (the GUI window spans 0..1, the
ground is at y = 0.1); time in its simulation time units, ``dt`` per step.
``distance`` is how far the head moved in x during the last training iteration's
forward pass: ``-loss_last - head_x0``, with ``head_x0 = x[0, head_id][0]``.
``distance_after_update`` is the same over the first ``steps`` steps of
``mass_spring.py``'s closing ``forward('final...')`` (run with the weights after the
last gradient step; it simulates ``2 * steps`` steps in all).

    python benchmarks/difftaichi_runner.py --difftaichi ~/src/difftaichi/examples --robot 2 --iters 100
    python benchmarks/difftaichi_runner.py --difftaichi PATH --iters 5 --threads 1 --json benchmarks/out/dt.json

Another benchmark can ``import difftaichi_runner`` (with ``benchmarks/`` on the path)
and call ``run(examples_dir, robot, iters, threads=None)``, which returns the dict
written as JSON.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

REQUIRED_FILES = ("mass_spring.py", "mass_spring_robot_config.py")

# Run in the child as ``python -c SHIM EXAMPLES_DIR ROBOT ITERS THREADS OUT_JSON``
# (THREADS empty for Taichi's default). Writes what it measured to OUT_JSON.
SHIM = r'''
import builtins, json, os, runpy, sys, time

t_start = (time.perf_counter(), time.process_time())
examples, robot, iters, threads, out_path = sys.argv[1:6]
robot, iters = int(robot), int(iters)

from mass_spring_robot_config import robots
if not 0 <= robot < len(robots):
    sys.exit("--robot: %d is not a robot of mass_spring_robot_config.py (0..%d)" % (robot, len(robots) - 1))

import taichi as ti


class NoGUI:
    """Stands in for taichi.GUI: any method accepts any arguments and does nothing."""
    running = True

    def __init__(self, *args, **kwargs):
        pass

    def __getattr__(self, name):
        return lambda *args, **kwargs: None


ti.GUI = NoGUI

if threads:
    _ti_init = ti.init

    def _init_cpu_threads(*args, **kwargs):
        kwargs["arch"] = ti.cpu
        kwargs["cpu_max_num_threads"] = int(threads)
        return _ti_init(*args, **kwargs)

    ti.init = _init_cpu_threads

marks = {}
records = []
_print = builtins.print


def _stamped_print(*args, **kwargs):
    wall, cpu = time.perf_counter(), time.process_time()
    if len(args) >= 4 and args[0] == "Iter=":
        records.append({"iteration": int(args[1]), "loss": float(args[3]), "wall_t": wall, "cpu_t": cpu})
    elif args and args[0] == "n_objects=" and "setup" not in marks:
        marks["setup"] = (wall, cpu)
    _print(*args, **kwargs)


builtins.print = _stamped_print
sys.argv = ["mass_spring.py", str(robot), "train", "--iters", str(iters)]
g = runpy.run_path(os.path.join(examples, "mass_spring.py"), run_name="__main__")
t_end = (time.perf_counter(), time.process_time())
builtins.print = _print

steps, head = int(g["steps"]), int(g["head_id"])
try:
    from taichi.lang import impl
    cfg = impl.current_cfg()
    arch, cpu_threads = str(cfg.arch).split(".")[-1], int(cfg.cpu_max_num_threads)
except Exception:
    arch = cpu_threads = None
with open(out_path, "w") as f:
    json.dump({
        "t_start": t_start, "t_setup": marks.get("setup", t_start), "t_end": t_end,
        "records": records, "steps": steps, "dt": float(g["dt"]), "head_id": head,
        "head_x0": float(g["x"][0, head][0]),
        "head_x_after_update": float(g["x"][steps - 1, head][0]),
        "n_objects": int(g["n_objects"]), "n_springs": int(g["n_springs"]),
        "taichi_version": ".".join(str(v) for v in ti.__version__),
        "arch": arch, "cpu_threads": cpu_threads,
    }, f)
'''


def check_arguments(examples_dir, robot, iters, threads=None):
    """Raise ValueError("--option: ...") naming the first bad argument; return the folder, resolved."""
    examples = Path(examples_dir).expanduser().resolve()
    if not examples.is_dir():
        raise ValueError(f"--difftaichi: {examples} is not a folder (give the examples/ folder of a "
                         "difftaichi checkout)")
    for name in REQUIRED_FILES:
        if not (examples / name).is_file():
            raise ValueError(f"--difftaichi: {examples} has no {name} (give the examples/ folder of a "
                             "difftaichi checkout)")
    if robot < 0:
        raise ValueError(f"--robot: must be >= 0, got {robot}")
    if iters < 1:
        raise ValueError(f"--iters: must be >= 1, got {iters}")
    if threads is not None and threads < 1:
        raise ValueError(f"--threads: must be >= 1, got {threads}")
    return examples


def _git(examples, *args):
    """Output of ``git -C examples ARGS``, stripped, or None if git fails."""
    try:
        done = subprocess.run(["git", "-C", str(examples), *args], capture_output=True, text=True,
                              timeout=30)
    except (OSError, subprocess.SubprocessError):
        return None
    return done.stdout.strip() if done.returncode == 0 else None


def source_info(examples):
    """Path (relative to this repository's root, so that a result names no machine's
    folders), git commit (None outside a git checkout), local changes to the two files,
    sha256s."""
    commit = _git(examples, "rev-parse", "HEAD")
    status = _git(examples, "status", "--porcelain", "--", *REQUIRED_FILES) if commit else None
    return {
        "path": os.path.relpath(examples, Path(__file__).resolve().parents[1]),
        "commit": commit,
        "modified": None if status is None else bool(status),
        "sha256": {name: hashlib.sha256((examples / name).read_bytes()).hexdigest()
                   for name in REQUIRED_FILES},
    }


def _median(values):
    return statistics.median(values) if values else None


def run(examples_dir, robot, iters, threads=None, quiet=False):
    """Train robot ``robot`` for ``iters`` iterations with DiffTaichi's mass_spring.py; return the results.

    ``threads``: Taichi CPU thread count (None: Taichi's default arch and thread count).
    ``quiet``: capture the child's output instead of passing it through (shown on failure).
    Raises ValueError for a bad argument, RuntimeError if the child fails.

    The dict holds: ``iterations`` (list of {iteration, loss, wall_s, cpu_s}; seconds),
    ``loss_first``, ``loss_last``, ``median_wall_s`` and ``median_cpu_s`` (seconds per
    iteration, over iterations 1..; None when iters == 1), ``first_iteration_wall_s``,
    ``steps``, ``dt`` and ``simulated_time`` (= steps * dt, simulation time units, per
    forward pass), ``head_id``, ``head_x0``, ``head_x_last`` (= -loss_last),
    ``distance`` (= head_x_last - head_x0), ``distance_after_update``, ``total_wall_s``
    and ``total_cpu_s`` (the whole child run after its start, including Taichi's import
    and the closing 2 * steps forward pass), ``robot``, ``iters``, ``threads``,
    ``n_objects``, ``n_springs``, ``taichi_version``, ``arch``, ``cpu_threads``,
    ``python`` and ``difftaichi`` (path, commit, modified, sha256 of the two files).
    """
    examples = check_arguments(examples_dir, robot, iters, threads)
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(examples), env.get("PYTHONPATH")) if p)
    env["PYTHONUNBUFFERED"] = "1"
    with tempfile.TemporaryDirectory(prefix="difftaichi_runner_") as work:
        out = Path(work) / "difftaichi_runner_child.json"
        command = [sys.executable, "-c", SHIM, str(examples), str(robot), str(iters),
                   "" if threads is None else str(threads), str(out)]
        done = subprocess.run(command, cwd=work, env=env, capture_output=quiet, text=True)
        if done.returncode != 0 or not out.is_file():
            tail = ""
            if quiet:
                lines = (done.stdout + done.stderr).strip().splitlines()
                tail = ":\n" + "\n".join(lines[-20:])
            raise RuntimeError(f"mass_spring.py failed in the child process (exit code {done.returncode})"
                               + (tail or "; its output is above"))
        child = json.loads(out.read_text())

    records = child["records"]
    if len(records) != iters:
        raise RuntimeError(f"expected {iters} 'Iter=' lines from mass_spring.py, saw {len(records)}")
    iterations = []
    previous = child["t_setup"]
    for r in records:
        iterations.append({"iteration": r["iteration"], "loss": r["loss"],
                           "wall_s": r["wall_t"] - previous[0], "cpu_s": r["cpu_t"] - previous[1]})
        previous = (r["wall_t"], r["cpu_t"])
    head_x_last = -iterations[-1]["loss"]
    return {
        "robot": robot,
        "iters": iters,
        "threads": threads,
        "loss_first": iterations[0]["loss"],
        "loss_last": iterations[-1]["loss"],
        "median_wall_s": _median([it["wall_s"] for it in iterations[1:]]),
        "median_cpu_s": _median([it["cpu_s"] for it in iterations[1:]]),
        "first_iteration_wall_s": iterations[0]["wall_s"],
        "steps": child["steps"],
        "dt": child["dt"],
        "simulated_time": child["steps"] * child["dt"],
        "head_id": child["head_id"],
        "head_x0": child["head_x0"],
        "head_x_last": head_x_last,
        "distance": head_x_last - child["head_x0"],
        "distance_after_update": child["head_x_after_update"] - child["head_x0"],
        "total_wall_s": child["t_end"][0] - child["t_start"][0],
        "total_cpu_s": child["t_end"][1] - child["t_start"][1],
        "n_objects": child["n_objects"],
        "n_springs": child["n_springs"],
        "taichi_version": child["taichi_version"],
        "arch": child["arch"],
        "cpu_threads": child["cpu_threads"],
        "python": sys.version.split()[0],
        "difftaichi": source_info(examples),
        "iterations": iterations,
    }


def _seconds(value):
    return "n/a (needs --iters >= 2)" if value is None else f"{value:.4f}"


def print_table(result):
    """Print the summary to stdout; return the width of the name column."""
    src = result["difftaichi"]
    rows = [
        ("DiffTaichi source", f"{src['path']} (commit {src['commit'] or 'unknown'}"
                              f"{', modified' if src['modified'] else ''})"),
        ("robot", f"{result['robot']} ({result['n_objects']} masses, {result['n_springs']} springs)"),
        ("Taichi", f"{result['taichi_version']}, arch {result['arch']}, {result['cpu_threads']} CPU threads"),
        ("iterations", str(result["iters"])),
        ("loss first / last", f"{result['loss_first']:.6f} / {result['loss_last']:.6f}"),
        ("first iteration wall s (compiles)", f"{result['first_iteration_wall_s']:.3f}"),
        ("median wall s / iteration (1..)", _seconds(result["median_wall_s"])),
        ("median CPU s / iteration (1..)", _seconds(result["median_cpu_s"])),
        ("head distance, last iteration", f"{result['distance']:.6f} (x {result['head_x0']:.4f} -> "
                                          f"{result['head_x_last']:.4f})"),
        ("head distance after last update", f"{result['distance_after_update']:.6f}"),
        ("simulated time (steps * dt)",
         f"{result['steps']} * {result['dt']:g} = {result['simulated_time']:.4f}"),
    ]
    width = max(len(name) for name, _ in rows)
    for name, value in rows:
        print(f"{name:<{width}}  {value}")
    return width


def main(argv=None):
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import output

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--difftaichi", required=True,
                        help="the examples/ folder of a difftaichi checkout (mass_spring.py, "
                        "mass_spring_robot_config.py)")
    p.add_argument("--robot", type=int, default=2,
                        help="robot id of mass_spring_robot_config.py (default 2)")
    p.add_argument("--iters", type=int, default=100, help="training iterations (default 100)")
    p.add_argument("--threads", type=int, default=None,
                        help="Taichi CPU threads (arch=cpu, cpu_max_num_threads); default: Taichi's")
    output.add_json(p, "difftaichi_runner")
    args = p.parse_args(argv)
    try:
        check_arguments(args.difftaichi, args.robot, args.iters, args.threads)
    except ValueError as error:
        print(f"{p.prog}: error: {error}", file=sys.stderr)
        return 2
    try:
        result = run(args.difftaichi, args.robot, args.iters, args.threads)
    except RuntimeError as error:
        print(f"{p.prog}: error: {error}", file=sys.stderr)
        return 1
    print()
    width = print_table(result)
    path = Path(args.json)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=1) + "\n")
    print(f"{'json':<{width}}  {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
