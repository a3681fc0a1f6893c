"""Implicit step (Eq. 15) on the cloth scene: massspring's matrix-free PCG against peers.

For each resolution, stiffness and precision: ms per implicit step (median over
steps after a warm-up step; compile time reported apart), CG iterations per step,
ms per CG iteration, spring-iterations per second. Peers, on the same states and
matrices in the same run (f64 only): SciPy assembled sparse matrix + Jacobi PCG,
Taichi's ti.linalg.MatrixFreeCG (matvec is a Taichi kernel; no preconditioner),
and a direct sparse LU (scipy factorized). Every solution is checked against the
assembled matrix: its relative residual ||A v - b|| / ||b|| must be at most the
tolerance (x1.05 for the peers whose stopping test uses the recursive residual),
and its difference from the direct solve is reported.

    python benchmarks/implicit_step.py --help
    python benchmarks/implicit_step.py --resolutions 32 64 128 --stiffness 1e4 --precision f64
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import peers  # noqa: E402

import massspring as ms  # noqa: E402
from massspring.io.files import write_json  # noqa: E402


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--resolutions", type=int, nargs="+", default=[32, 64, 128, 256])
    p.add_argument("--stiffness", type=float, nargs="+", default=[1e4, 1e6])
    p.add_argument("--precision", nargs="+", default=["f64", "f32"], choices=["f64", "f32"])
    p.add_argument("--tol", type=float, default=1e-6, help="relative CG tolerance (all solvers)")
    p.add_argument("--steps", type=int, default=5, help="timed steps per case (after one warm-up step)")
    p.add_argument("--peer-steps", type=int, default=3, help="steps on which the peers are timed")
    p.add_argument("--loops", choices=["auto", "serial", "parallel"], default="auto",
                   help="massspring CG driver: whole-solve serial kernel, parallel kernels, or by size")
    p.add_argument("--peers", nargs="*", default=["scipy", "taichi-cg", "direct"],
                   choices=["scipy", "taichi-cg", "direct"])
    p.add_argument("--max-scipy", type=int, default=256, help="largest resolution for SciPy CG")
    p.add_argument("--max-taichi-cg", type=int, default=128, help="largest resolution for ti.linalg.MatrixFreeCG")
    p.add_argument("--max-direct", type=int, default=256, help="largest resolution for the direct solve")
    p.add_argument("--json", default="benchmarks/results/implicit_step.json")
    return p.parse_args(argv)


def cloth(resolution, stiffness):
    return ms.load_scene("cloth").with_params(resolution=resolution, stiffness=stiffness)


def relative_residual(matrix, rhs, v):
    return float(np.linalg.norm(matrix @ v - rhs) / np.linalg.norm(rhs))


def run_case(args, resolution, stiffness, precision):
    scene = cloth(resolution, stiffness)
    dt = 1.0 / 60.0
    sim = scene.simulation(integrator="implicit", dt=dt, precision=precision, cg_tol=args.tol,
                           loops=args.loops)
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

    # The peers run after massspring's timed steps: ti.linalg.MatrixFreeCG builds and
    # destroys Taichi fields on every call, which makes later kernel launches in the
    # process recompile; interleaving it would slow the steps measured above.
    residuals = []
    peer_rows = {name: {"s": [], "iterations": [], "residual": [], "diff": []} for name in args.peers}
    peer_rows["massspring-diff"] = []
    taichi_cg = None
    for x, v, v_ours in states:
        matrix, rhs, free = peers.assemble_system(model, x, v, dt)
        residuals.append(relative_residual(matrix, rhs, v_ours[free].ravel()))
        reference = None
        if "direct" in args.peers and resolution <= args.max_direct:
            t0 = time.perf_counter()
            reference = peers.scipy_direct(matrix, rhs)
            peer_rows["direct"]["s"].append(time.perf_counter() - t0)
            peer_rows["direct"]["residual"].append(relative_residual(matrix, rhs, reference))
            peer_rows["massspring-diff"].append(
                float(np.linalg.norm(v_ours[free].ravel() - reference) / np.linalg.norm(reference)))
        if "scipy" in args.peers and resolution <= args.max_scipy:
            t0 = time.perf_counter()
            matrix2, rhs2, _ = peers.assemble_system(model, x, v, dt)
            sol, its = peers.scipy_pcg(matrix2, rhs2, v[free].ravel(), args.tol)
            peer_rows["scipy"]["s"].append(time.perf_counter() - t0)
            peer_rows["scipy"]["iterations"].append(its)
            peer_rows["scipy"]["residual"].append(relative_residual(matrix, rhs, sol))
            if reference is not None:
                peer_rows["scipy"]["diff"].append(float(np.linalg.norm(sol - reference) / np.linalg.norm(reference)))
    for x, v, _ in states:
        if "taichi-cg" not in args.peers or resolution > args.max_taichi_cg:
            break
        matrix, rhs, free = peers.assemble_system(model, x, v, dt)
        taichi_cg = taichi_cg or peers.TaichiMatrixFreeCG(model)
        t0 = time.perf_counter()
        sol, its = taichi_cg.solve(x, v, dt, args.tol)
        peer_rows["taichi-cg"]["s"].append(time.perf_counter() - t0)
        peer_rows["taichi-cg"]["iterations"].append(its)
        sol = sol[free].ravel()
        peer_rows["taichi-cg"]["residual"].append(relative_residual(matrix, rhs, sol))
        reference = peers.scipy_direct(matrix, rhs) if resolution <= args.max_direct else None
        if reference is not None:
            peer_rows["taichi-cg"]["diff"].append(float(np.linalg.norm(sol - reference) / np.linalg.norm(reference)))

    step_ms = 1e3 * statistics.median(times)
    it = statistics.median(iters)
    # The peers solve the states of the first ``peer_steps`` steps: compare on those.
    same_ms = 1e3 * statistics.median(times[:len(states)]) if states else step_ms
    same_it = statistics.median(iters[:len(states)]) if states else it
    row = {
        "resolution": resolution, "stiffness": stiffness, "precision": precision,
        "particles": model.n_particles, "springs": model.n_springs, "tol": args.tol,
        "loops": sim.loops,
        "step_ms": step_ms, "iterations": it, "ms_per_iteration": step_ms / max(it, 1),
        "spring_iterations_per_s": model.n_springs * it / (step_ms / 1e3),
        "compile_s": max(first - statistics.median(times), 0.0),
        "converged_all": all(st.converged for st in solver),
        "solver_residual_max": max(st.residual for st in solver),
        "reasons": sorted({st.reason for st in solver}),
        "residual_max": max(residuals) if residuals else None,
        "diff_from_direct": max(peer_rows["massspring-diff"]) if peer_rows["massspring-diff"] else None,
        "peers": {},
    }
    for name in args.peers:
        data = peer_rows[name]
        if not data["s"]:
            continue
        ms_step = 1e3 * statistics.median(data["s"])
        its = statistics.median(data["iterations"]) if data["iterations"] else None
        row["peers"][name] = {
            "step_ms": ms_step, "iterations": its,
            "ms_per_iteration": ms_step / its if its else None,
            "residual_max": max(data["residual"]),
            "diff_from_direct": max(data["diff"]) if data["diff"] else None,
            "speedup": ms_step / same_ms,
            "massspring_step_ms": same_ms, "massspring_iterations": same_it,
        }
    return row


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
          f"{row['loops']:>8s} {row['step_ms']:9.2f} {row['iterations']:6.0f} {row['ms_per_iteration']:8.4f} "
          f"{row['spring_iterations_per_s'] / 1e6:9.1f} {row['compile_s']:7.2f}  {peers_text}"
          + ("" if row["converged_all"] else
             f"  [{'/'.join(row['reasons'])}, residual {row['solver_residual_max']:.1e}]"), flush=True)


def main(argv=None):
    args = parse_args(argv)
    print(f"{'res':>5s} {'ks':>8s} {'prec':>4s} {'springs':>8s} {'loops':>8s} {'ms/step':>9s} {'iters':>6s} "
          f"{'ms/iter':>8s} {'Msi/s':>9s} {'jit s':>7s}  peers on the first --peer-steps states "
          f"(ms/step, massspring speed-up on the same states, iterations: peer vs massspring)")
    rows, failures = [], []
    for precision in args.precision:
        for stiffness in args.stiffness:
            for resolution in args.resolutions:
                row = run_case(args, resolution, stiffness, precision)
                print_row(row)
                failures += [f"res {resolution} ks {stiffness:g} {precision}: {p}" for p in check(row, args.tol)]
                rows.append(row)
    write_json(args.json, {"tol": args.tol, "rows": rows})
    print(f"wrote {args.json}")
    for f in failures:
        print("CHECK FAILED:", f)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
