"""Peak memory of a run against ``massspring.support.memory``'s estimate, and how fast a run
too large for the machine is refused.

Table 1: for each scene, size and solver, a fresh process builds the model, makes
the Simulation and takes one step; the peak resident memory it adds over a warm
Taichi runtime (``VmHWM``) is set beside ``memory.run_bytes`` (margin included)
and the per-particle/per-spring figures the estimate is fitted to.

Table 2: ``massspring run cloth --set resolution=R --steps 1`` for large R, with and
without an address-space limit (``ulimit -v``): exit code, wall time and peak RSS.

    python benchmarks/memory.py
    python benchmarks/memory.py --refusals 3000 4000 5000 6000 --ulimit-kb 12000000
"""

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

from massspring.io.files import write_json
import output

CASES = [("cloth", "resolution", 150), ("cloth", "resolution", 300), ("chain", "count", 40000),
         ("chain", "count", 160000), ("cube", "resolution", 25), ("cube", "resolution", 40)]
ROOT = Path(__file__).resolve().parent.parent  # the repository: messages name files relative to it
SOLVERS = [("explicit", None), ("implicit", "block-jacobi"), ("implicit", "multigrid"), ("implicit", "multigrid-f32")]


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cases", nargs="*", default=[f"{s}:{k}={v}" for s, k, v in CASES],
                   help="SCENE:KEY=VALUE (default: %(default)s)")
    p.add_argument("--refusals", nargs="*", type=int, default=[3000, 4000, 5000, 6000],
                   help="cloth resolutions run to check the refusal")
    p.add_argument("--ulimit-kb", type=int, default=12_000_000, help="address-space limit of the second pass")
    output.add_json(p, "memory")
    p.add_argument("--worker", help=argparse.SUPPRESS)
    return p.parse_args(argv)


def own_peak():
    """This process's peak RSS in bytes (VmHWM; ru_maxrss of a child starts from its parent's)."""
    with open("/proc/self/status") as fh:
        return next(int(line.split()[1]) * 1024 for line in fh if line.startswith("VmHWM:"))


def worker(spec):
    """Run one case in this (fresh) process and print its figures as JSON."""
    import massspring as ms
    from massspring.support import memory

    case, integrator, preconditioner = spec.split("|")
    scene_name, _, setting = case.partition(":")
    key, _, value = setting.partition("=")
    warm = ms.load_scene("spring").simulation(integrator=integrator)
    warm.step()
    warm.close()
    base = own_peak()
    model = ms.load_scene(scene_name).with_params(**{key: int(value)}).model()
    options = {"preconditioner": preconditioner} if preconditioner != "-" else {}
    sim = ms.Simulation(model, integrator=integrator, **options)
    try:
        sim.step()
    except ms.DivergenceError:  # the step ran (and allocated) all the same
        pass
    added = own_peak() - base
    solver = None if preconditioner == "-" else preconditioner
    print(json.dumps({"case": case, "integrator": integrator, "preconditioner": solver,
                      "particles": model.n_particles, "springs": model.n_springs, "added_bytes": added,
                      "estimate_bytes": memory.run_bytes(model.n_particles, model.n_springs, solver)}))


def measure(case, integrator, preconditioner):
    spec = f"{case}|{integrator}|{preconditioner or '-'}"
    out = subprocess.run([sys.executable, __file__, "--worker", spec], capture_output=True, text=True)
    if out.returncode:
        raise RuntimeError(out.stderr)
    return json.loads(out.stdout.strip().splitlines()[-1])


def refusal(resolution, ulimit_kb):
    def limit():
        if ulimit_kb:
            resource.setrlimit(resource.RLIMIT_AS, (ulimit_kb * 1024, ulimit_kb * 1024))

    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "massspring", "run", "cloth", "--set", f"resolution={resolution}",
                             "--steps", "1", "--quiet"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            preexec_fn=limit)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    stderr = proc.stderr.read().decode().strip().replace(f"{ROOT}/", "")  # paths relative to the repository
    return {"resolution": resolution, "ulimit_kb": ulimit_kb, "exit": os.waitstatus_to_exitcode(status),
            "wall_s": wall, "peak_rss_bytes": usage.ru_maxrss * 1024, "message": stderr.splitlines()[-1:]}


def main(argv=None):
    args = parse_args(argv)
    if args.worker:
        worker(args.worker)
        return 0
    rows = []
    print(f"{'case':>24s} {'solver':>22s} {'particles':>10s} {'springs':>10s} {'added MB':>9s} {'estimate MB':>11s} "
          f"{'estimate/added':>14s}")
    for case in args.cases:
        for integrator, preconditioner in SOLVERS:
            row = measure(case, integrator, preconditioner)
            rows.append(row)
            print(f"{case:>24s} {integrator + ' ' + (preconditioner or ''):>22s} {row['particles']:10d} "
                  f"{row['springs']:10d} {row['added_bytes'] / 1e6:9.0f} {row['estimate_bytes'] / 1e6:11.0f} "
                  f"{row['estimate_bytes'] / max(row['added_bytes'], 1):14.2f}", flush=True)
    refusals = []
    print(f"\n{'resolution':>10s} {'ulimit -v KB':>12s} {'exit':>4s} {'wall s':>7s} {'peak RSS MB':>11s}")
    for resolution in args.refusals:
        for ulimit_kb in (None, args.ulimit_kb):
            row = refusal(resolution, ulimit_kb)
            refusals.append(row)
            print(f"{resolution:10d} {str(ulimit_kb or '-'):>12s} {row['exit']:4d} {row['wall_s']:7.2f} "
                  f"{row['peak_rss_bytes'] / 1e6:11.0f}", flush=True)
    write_json(args.json, {"runs": rows, "refusals": refusals})
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
