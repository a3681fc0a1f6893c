"""CG iterations and cost against size, per preconditioner: cloths and an irregular mesh.

Cases: the cloth scene at ``--resolutions`` (32^2..512^2) and ``--stiffness`` (1e4,
1e6), and a Delaunay disc of ``--disc`` random points (edges as springs, see
``peers.disc_model``), each solved with ``--solvers``: massspring's implicit step
with ``preconditioner`` none, block-jacobi and multigrid, and the peer ``pyamg``
(SciPy matrix + pyamg smoothed aggregation, 3x3 blocks, translations as
near-nullspace, rebuilt every step: assembly + setup + solve timed). dt = 1/60,
f64, relative tolerance 1e-6, definiteness fix on.

Each case runs in a fresh process (peak RSS is per process): one warm-up step
(compilation), then up to ``--steps`` timed steps, fewer if they pass ``--budget``
seconds. Reported: CG iterations per step (mean and max), ms per step (median),
the multigrid's per-step setup (its share of the step), bytes of Taichi fields and
peak RSS growth per spring. pyamg solves the states of a multigrid run.
Children run with OPENBLAS_NUM_THREADS=1 and OMP_NUM_THREADS=1: pyamg's many small
dense products slow down by up to 20x when BLAS threads compete on a busy machine,
and Taichi does not use BLAS.

    python benchmarks/scaling.py --help
    python benchmarks/scaling.py --resolutions 32 64 128 --stiffness 1e4 --solvers block-jacobi multigrid
"""

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from massspring.io.files import write_json  # noqa: E402
import output  # noqa: E402

SOLVERS = ("none", "block-jacobi", "multigrid", "pyamg")


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--resolutions", type=int, nargs="+", default=[32, 64, 128, 256, 512])
    p.add_argument("--stiffness", type=float, nargs="+", default=[1e4, 1e6])
    p.add_argument("--disc", type=int, default=20000, help="points of the irregular mesh (0: none)")
    p.add_argument("--solvers", nargs="+", default=list(SOLVERS), choices=SOLVERS)
    p.add_argument("--steps", type=int, default=4, help="timed steps per case, at most")
    p.add_argument("--budget", type=float, default=120.0, help="seconds of timed steps per case, about")
    output.add_json(p, "scaling")
    p.add_argument("--child", nargs=4, metavar=("MESH", "SIZE", "KS", "SOLVER"), help=argparse.SUPPRESS)
    return p.parse_args(argv)


def child_env():
    return dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")


def peak_rss_bytes():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # Linux reports KiB


def build_model(mesh, size, stiffness):
    import massspring as ms
    import peers

    if mesh == "disc":
        return peers.disc_model(size, stiffness)
    return ms.load_scene("cloth").with_params(resolution=size, stiffness=stiffness).model()


def child(mesh, size, stiffness, solver, steps, budget):
    import numpy as np

    import massspring as ms
    import peers
    from massspring.device import ensure_taichi

    ensure_taichi()
    model = build_model(mesh, size, stiffness)
    baseline = peak_rss_bytes()
    dt = 1 / 60
    sim = ms.Simulation(model, integrator="implicit", dt=dt, preconditioner="multigrid" if solver == "pyamg" else solver,
                        cg_max_iter=100000)
    sim.step(1)
    times, its, setups, states = [], [], [], []
    spent = 0.0
    while len(times) < steps and (spent < budget or not times):
        x, v = sim.positions, sim.velocities
        t0 = time.perf_counter()
        sim.step(1)
        times.append(time.perf_counter() - t0)
        spent += times[-1]
        its.append(sim.solver_stats.iterations)
        setups.append(sim.solver_stats.setup_s)
        states.append((x, v))
        if not sim.solver_stats.converged:
            break
    row = {"mesh": mesh, "size": size, "stiffness": stiffness, "solver": solver, "particles": model.n_particles,
           "springs": model.n_springs, "steps": len(times), "converged": sim.cg_failures == 0}
    if solver == "pyamg":
        peer_times, peer_its = [], []
        for x, v in states:
            t0 = time.perf_counter()
            matrix, rhs, free = peers.assemble_system(model, x, v, dt)
            _, count = peers.pyamg_pcg(matrix, rhs, v[free].ravel(), 1e-6)
            peer_times.append(time.perf_counter() - t0)
            peer_its.append(count)
        times, its, setups = peer_times, peer_its, [0.0] * len(peer_times)
    else:
        info = sim.info()
        row["array_bytes_per_spring"] = info["bytes"] / model.n_springs
        row["rss_bytes_per_spring"] = (peak_rss_bytes() - baseline) / model.n_springs
    row.update(ms_per_step=1e3 * statistics.median(times), iterations_mean=float(np.mean(its)),
               iterations_max=int(max(its)), setup_ms=1e3 * statistics.median(setups),
               setup_share=statistics.median(setups) / statistics.median(times))
    return row


def main(argv=None):
    args = parse_args(argv)
    if args.child:
        mesh, size, ks, solver = args.child
        print(json.dumps(child(mesh, int(size), float(ks), solver, args.steps, args.budget)))
        return 0
    cases = [("cloth", r, ks) for ks in args.stiffness for r in args.resolutions]
    if args.disc:
        cases.append(("disc", args.disc, 1e4))
    print(f"{'mesh':>6s} {'size':>6s} {'ks':>7s} {'springs':>8s} {'solver':>13s} {'its mean':>8s} {'max':>5s} "
          f"{'ms/step':>9s} {'setup':>6s} {'arrays B/spr':>12s}")
    rows = []
    for mesh, size, ks in cases:
        for solver in args.solvers:
            out = subprocess.run([sys.executable, __file__, "--child", mesh, str(size), str(ks), solver,
                                  "--steps", str(args.steps), "--budget", str(args.budget)],
                                 capture_output=True, text=True, env=child_env())
            if out.returncode:
                print(out.stderr[-3000:], file=sys.stderr)
                return 1
            row = json.loads(out.stdout.strip().splitlines()[-1])
            rows.append(row)
            arrays = f"{row['array_bytes_per_spring']:12.0f}" if "array_bytes_per_spring" in row else f"{'-':>12s}"
            print(f"{mesh:>6s} {size:6d} {ks:7.0e} {row['springs']:8d} {solver:>13s} {row['iterations_mean']:8.1f} "
                  f"{row['iterations_max']:5d} {row['ms_per_step']:9.1f} {row['setup_share']:6.0%} {arrays}"
                  + ("" if row["converged"] else "  (not converged)"), flush=True)
            write_json(args.json, {"rows": rows})
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
