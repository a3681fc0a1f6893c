"""Implicit step (Eq. 15) on the cloth scene: massspring's matrix-free PCG against peers.

For each resolution, stiffness, precision and ``--preconditioners``: ms per implicit
step (median over steps after a warm-up step; compile time reported apart), CG
iterations per step, ms per CG iteration, spring-iterations per second. Peers, on
the states of the first preconditioner's run (f64 only), each timed with its
assembly: SciPy assembled sparse matrix + Jacobi PCG; SciPy CG preconditioned by
pyamg's smoothed aggregation (3x3 blocks, translations as near-nullspace, its setup
paid every step since the matrix changes); Taichi's ti.linalg.MatrixFreeCG (matvec
is a Taichi kernel; no preconditioner); a direct sparse LU (scipy factorized).
Every solver stops at ``--tol`` times its first residual ||b - A v_n|| (massspring's
CG test; the peers are given the same), and every solution is checked against the
assembled matrix: ||A v - b|| / ||b - A v_n|| must be at most the tolerance (x1.05
for the peers whose stopping test uses the recursive residual), and its difference
from the direct solve is reported. BLAS runs single-threaded (OPENBLAS_NUM_THREADS=1 unless set):
pyamg's many small dense products slow down severalfold when BLAS threads compete
with each other on 2 cores.

    python benchmarks/implicit_step.py --help
    python benchmarks/implicit_step.py --resolutions 32 64 128 --stiffness 1e4 --precision f64
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import peers  # noqa: E402

import massspring as ms  # noqa: E402
from massspring.io.files import write_json  # noqa: E402
import output  # noqa: E402

PEERS = ("scipy", "pyamg", "taichi-cg", "direct")


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--resolutions", type=int, nargs="+", default=[32, 64, 128, 256])
    p.add_argument("--stiffness", type=float, nargs="+", default=[1e4, 1e6])
    p.add_argument("--precision", nargs="+", default=["f64", "f32"], choices=["f64", "f32"])
    p.add_argument("--preconditioners", nargs="+", default=["block-jacobi", "multigrid"],
                   choices=["block-jacobi", "multigrid", "none"])
    p.add_argument("--tol", type=float, default=1e-6, help="relative CG tolerance (all solvers)")
    p.add_argument("--steps", type=int, default=5, help="timed steps per case (after one warm-up step)")
    p.add_argument("--peer-steps", type=int, default=3, help="steps on which the peers are timed")
    p.add_argument("--loops", choices=["auto", "serial", "parallel"], default="auto",
                   help="massspring CG driver: whole-solve serial kernel, parallel kernels, or by size")
    p.add_argument("--peers", nargs="*", default=list(PEERS), choices=PEERS)
    p.add_argument("--max-scipy", type=int, default=256, help="largest resolution for SciPy CG")
    p.add_argument("--max-pyamg", type=int, default=512, help="largest resolution for SciPy + pyamg")
    p.add_argument("--max-taichi-cg", type=int, default=128, help="largest resolution for ti.linalg.MatrixFreeCG")
    p.add_argument("--max-direct", type=int, default=256, help="largest resolution for the direct solve")
    output.add_json(p, "implicit_step")
    return p.parse_args(argv)


def cloth(resolution, stiffness):
    return ms.load_scene("cloth").with_params(resolution=resolution, stiffness=stiffness)


def relative_residual(matrix, rhs, v, v0):
    """||A v - b|| relative to the first residual ||b - A v0|| (v0 = v_n, where every solver starts)."""
    return float(np.linalg.norm(matrix @ v - rhs)) / peers.first_residual(matrix, rhs, v0)


def run_massspring(args, scene, precision, preconditioner, dt):
    """One massspring run: its row and the states (x, v before, v after) of its first
    ``peer_steps`` steps (f64)."""
    sim = scene.simulation(integrator="implicit", dt=dt, precision=precision, cg_tol=args.tol,
                           loops=args.loops, preconditioner=preconditioner)
    model = sim.model
    t0 = time.perf_counter()
    sim.step()
    first = time.perf_counter() - t0
    times, iters, states, solver = [], [], [], []
    for k in range(args.steps):
        x, v = sim.positions, sim.velocities
        t0 = time.perf_counter()
        sim.step()
        times.append(time.perf_counter() - t0)
        iters.append(sim.solver_stats.iterations)
        solver.append(sim.solver_stats)
        if precision == "f64" and k < args.peer_steps:
            states.append((x, v, sim.velocities))
    setup = [st.setup_s for st in solver]
    sim.close()
    residuals = []
    for x, v, v_ours in states:
        matrix, rhs, free = peers.assemble_system(model, x, v, dt)
        residuals.append(relative_residual(matrix, rhs, v_ours[free].ravel(), v[free].ravel()))
    step_ms = 1e3 * statistics.median(times)
    it = statistics.median(iters)
    return {
        "preconditioner": preconditioner, "particles": model.n_particles, "springs": model.n_springs,
        "tol": args.tol, "loops": sim.loops,
        "step_ms": step_ms, "iterations": it, "ms_per_iteration": step_ms / max(it, 1),
        "setup_share": statistics.median(setup) * 1e3 / step_ms,
        "spring_iterations_per_s": model.n_springs * it / (step_ms / 1e3),
        "compile_s": max(first - statistics.median(times), 0.0),
        "converged_all": all(st.converged for st in solver),
        "solver_residual_max": max(st.residual for st in solver),
        "reasons": sorted({st.reason for st in solver}),
        "residual_max": max(residuals) if residuals else None,
        # the peers solve the states of the first ``peer_steps`` steps: compared on those
        "same_ms": 1e3 * statistics.median(times[:len(states)]) if states else step_ms,
        "same_iterations": statistics.median(iters[:len(states)]) if states else it,
    }, states


def run_peers(args, model, states, dt, resolution):
    """Each peer on ``states``: {name: {"s", "iterations", "residual", "diff"}}, and the
    massspring solutions' distances from the direct solve."""
    data = {name: {"s": [], "iterations": [], "residual": [], "diff": []} for name in args.peers}
    ours_diff = []
    limits = {"scipy": args.max_scipy, "pyamg": args.max_pyamg, "direct": args.max_direct}
    for x, v, v_ours in states:
        matrix, rhs, free = peers.assemble_system(model, x, v, dt)
        reference = None
        if "direct" in args.peers and resolution <= args.max_direct:
            t0 = time.perf_counter()
            reference = peers.scipy_direct(matrix, rhs)
            data["direct"]["s"].append(time.perf_counter() - t0)
            data["direct"]["residual"].append(relative_residual(matrix, rhs, reference, v[free].ravel()))
            ours_diff.append(float(np.linalg.norm(v_ours[free].ravel() - reference) / np.linalg.norm(reference)))
        for name, solve in (("scipy", peers.scipy_pcg), ("pyamg", peers.pyamg_pcg)):
            if name not in args.peers or resolution > limits[name]:
                continue
            t0 = time.perf_counter()
            matrix2, rhs2, _ = peers.assemble_system(model, x, v, dt)
            sol, its = solve(matrix2, rhs2, v[free].ravel(), args.tol)
            data[name]["s"].append(time.perf_counter() - t0)
            data[name]["iterations"].append(its)
            data[name]["residual"].append(relative_residual(matrix, rhs, sol, v[free].ravel()))
            if reference is not None:
                data[name]["diff"].append(float(np.linalg.norm(sol - reference) / np.linalg.norm(reference)))
    # ti.linalg.MatrixFreeCG builds and destroys Taichi fields on every call, which makes
    # later kernel launches in the process recompile: it runs after everything else.
    taichi_cg = None
    for x, v, _ in states:
        if "taichi-cg" not in args.peers or resolution > args.max_taichi_cg:
            break
        matrix, rhs, free = peers.assemble_system(model, x, v, dt)
        taichi_cg = taichi_cg or peers.TaichiMatrixFreeCG(model)
        t0 = time.perf_counter()
        sol, its = taichi_cg.solve(x, v, dt, args.tol)
        data["taichi-cg"]["s"].append(time.perf_counter() - t0)
        data["taichi-cg"]["iterations"].append(its)
        sol = sol[free].ravel()
        data["taichi-cg"]["residual"].append(relative_residual(matrix, rhs, sol, v[free].ravel()))
        reference = peers.scipy_direct(matrix, rhs) if resolution <= args.max_direct else None
        if reference is not None:
            data["taichi-cg"]["diff"].append(float(np.linalg.norm(sol - reference) / np.linalg.norm(reference)))
    return data, ours_diff


def run_case(args, resolution, stiffness, precision):
    """Rows of one (resolution, stiffness, precision): one per preconditioner, each with
    the peers' times and its speed-up over them on the same states."""
    scene = cloth(resolution, stiffness)
    dt = 1.0 / 60.0
    rows, states = [], None
    for preconditioner in args.preconditioners:
        row, mine = run_massspring(args, scene, precision, preconditioner, dt)
        row.update(resolution=resolution, stiffness=stiffness, precision=precision)
        rows.append(row)
        states = states if states is not None else mine
    data, ours_diff = run_peers(args, scene.model(), states or [], dt, resolution)
    for row in rows:
        row["diff_from_direct"] = max(ours_diff) if ours_diff and row is rows[0] else None
        row["peers"] = {}
        for name in args.peers:
            if not data[name]["s"]:
                continue
            ms_step = 1e3 * statistics.median(data[name]["s"])
            its = statistics.median(data[name]["iterations"]) if data[name]["iterations"] else None
            row["peers"][name] = {
                "step_ms": ms_step, "iterations": its, "ms_per_iteration": ms_step / its if its else None,
                "residual_max": max(data[name]["residual"]),
                "diff_from_direct": max(data[name]["diff"]) if data[name]["diff"] else None,
                "speedup": ms_step / row["same_ms"],
                "massspring_step_ms": row["same_ms"], "massspring_iterations": row["same_iterations"],
            }
    return rows


def check(row, tol):
    """Every solver's solution must satisfy the tolerance on the assembled matrix."""
    problems = []
    if row["residual_max"] is not None and row["residual_max"] > tol:
        problems.append(f"massspring residual {row['residual_max']:.2e} > {tol:g}")
    for name, peer in row["peers"].items():
        limit = tol if name == "direct" else 1.05 * tol
        if peer["residual_max"] > limit:
            problems.append(f"{name} residual {peer['residual_max']:.2e} > {limit:.3g}")
    return problems


def print_row(row):
    peers_text = "  ".join(
        f"{name} {p['step_ms']:.1f} ms ({p['speedup']:.1f}x" + (f", {p['iterations']:.0f} vs {p['massspring_iterations']:.0f} it" if p["iterations"] else "") + ")"
        for name, p in row["peers"].items())
    print(f"{row['resolution']:5d} {row['stiffness']:8.0e} {row['precision']:>4s} {row['springs']:8d} "
          f"{row['preconditioner']:>12s} {row['loops']:>8s} {row['step_ms']:9.2f} {row['iterations']:6.0f} {row['ms_per_iteration']:8.4f} "
          f"{row['spring_iterations_per_s'] / 1e6:9.1f} {row['compile_s']:7.2f}  {peers_text}"
          + ("" if row["converged_all"] else
             f"  [{'/'.join(row['reasons'])}, residual {row['solver_residual_max']:.1e}]"), flush=True)


def main(argv=None):
    args = parse_args(argv)
    print(f"{'res':>5s} {'ks':>8s} {'prec':>4s} {'springs':>8s} {'precond':>12s} {'loops':>8s} {'ms/step':>9s} {'iters':>6s} "
          f"{'ms/iter':>8s} {'Msi/s':>9s} {'jit s':>7s}  peers on the first --peer-steps states "
          f"(ms/step, massspring speed-up on the same states, iterations: peer vs massspring)")
    rows, failures = [], []
    for precision in args.precision:
        for stiffness in args.stiffness:
            for resolution in args.resolutions:
                for row in run_case(args, resolution, stiffness, precision):
                    print_row(row)
                    failures += [f"res {resolution} ks {stiffness:g} {precision} {row['preconditioner']}: {p}"
                                 for p in check(row, args.tol)]
                    rows.append(row)
    write_json(args.json, {"tol": args.tol, "rows": rows})
    print(f"wrote {args.json}")
    for f in failures:
        print("CHECK FAILED:", f)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
