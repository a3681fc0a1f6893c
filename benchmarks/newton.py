"""Newton-solved backward Euler and BDF2 against the linearised implicit step (seed Eq. 15).

Tables (all f64, this machine):

1. energy: the shipped undamped ``stiffchain`` over 2 s at dt 0.01 and 0.002, the
   largest total energy above its start (J) and at the end, per integrator;
2. residual: one step from a stretched, moving ``stiffchain`` state, the backward-Euler
   equations' residual ||M (v1 - v0) - dt f(x1, v1)|| relative to ||dt f(x0, v0)||;
3. order: end-time position error against RK4 at dt / 10 of the finest on ``chain``
   (0.25 s, dt 1/2000 .. 1/16000) and the observed orders;
4. terminal velocity: a particle with linear drag and wind after 30 s at dt 0.05,
   relative error against m g / c + wind, at default tolerances;
5. cloth: ``cloth`` at ``--resolution`` (dt 1/60, ks 1e4, multigrid), median step
   time of each integrator over ``--steps`` steps after a warm-up step, measured
   interleaved in one process, mean Newton iterations and CG iterations per step, and
   the ratio to the linearised step;
6. damping: the shipped ``cloth`` (32 x 32) with its spring damping raised from 2 to
   2,000 N s/m, 20 backward-Euler and BDF2 steps at dt 1/60, and one at dt 1 s with
   1e9: Newton iterations per step, steps that missed ``newton_tol`` and the end's
   kinetic energy (how far the iteration is from stalling or running away);
7. tolerance (not in the default set: 10 minutes at 128 x 128): what ``newton_tol``
   buys. The cloth of table 5, backward Euler and BDF2 at newton_tol 1e-2, 3e-3 and
   1e-3 timed interleaved with the linearised step: Newton iterations and ms per step,
   and the largest distance (m) of the end positions from the same integrator's run at
   newton_tol 1e-6 (which takes nearly all of newton_max_iter's 50 iterations a step),
   beside backward Euler's distance from a run at dt / 2 (the time step's own error,
   for scale); and at each tolerance the residual of table 2's stiffchain step and the
   shipped stiffchain's largest energy above its start over 2 s at dt 1/60;
8. curvature (not in the default set; SciPy): why Newton is slow where the cloth folds.
   The cloth of table 5 run with backward Euler at default settings; from the state
   before the step that took the most Newton iterations, that step again at
   newton_tol 1e-9 (at most 400 iterations, cg_tol 1e-10); at its first iterate
   x_n + dt v_n and at its last: the springs in compression, the smallest eigenvalues
   of the step's Hessian M - dt D - dt^2 K with the true K (Eq. 13) and with the
   definiteness fix's (as multiples of the particles' mass), and the smallest mu of
   H_true y = mu H_fixed y: near the solution Newton with the fixed Hessian multiplies
   the error along y by 1 - mu an iteration. (The matrices are Eq. 15's A as
   ``peers.assemble_system`` builds it, spring damping along the springs at x; the
   step's own takes it at x_n + dt v_n.)

    python benchmarks/newton.py                       # all tables, cloth 128 x 128
    python benchmarks/newton.py --tables cloth --resolution 64 --steps 10
    python benchmarks/newton.py --json benchmarks/results/newton.json
    python benchmarks/newton.py --tables tolerance --json benchmarks/results/newton_tolerance.json
    python benchmarks/newton.py --tables curvature --resolution 64 --json benchmarks/results/newton_curvature.json
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import output  # noqa: E402
import peers  # noqa: E402

import massspring as ms  # noqa: E402
from massspring.io.files import write_json  # noqa: E402

NEWTON = ("backward-euler", "bdf2")
TABLES = ("energy", "residual", "order", "terminal", "cloth", "damping")
EXTRA_TABLES = ("tolerance", "curvature")
TOLERANCES = (1e-2, 3e-3, 1e-3)  # the tolerance table's newton_tol values
TIGHT = 1e-6  # its reference run's


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--tables", nargs="+", default=list(TABLES), choices=TABLES + EXTRA_TABLES)
    p.add_argument("--resolution", type=int, default=128, help="cloth, tolerance and curvature tables: grid "
                   "resolution (default 128)")
    p.add_argument("--steps", type=int, default=20, help="cloth and tolerance tables: timed steps per "
                   "integrator; curvature: steps searched (default 20)")
    output.add_json(p, "newton")
    return p.parse_args(argv)


def forces(model, x, v):
    """Total force (n, 3): springs, dampers, gravity and drag, in numpy (independent of the kernels)."""
    i, j = model.springs[:, 0], model.springs[:, 1]
    d = x[j] - x[i]
    length = np.linalg.norm(d, axis=1)
    n = np.divide(d, length[:, None], out=np.zeros_like(d), where=length[:, None] > 1e-12)
    tension = model.stiffness * (length - model.rest_lengths) + model.damping * np.sum((v[j] - v[i]) * n, axis=1)
    f = model.masses[:, None] * model.gravity - model.drag * (v - model.wind)
    np.add.at(f, i, tension[:, None] * n)
    np.add.at(f, j, -tension[:, None] * n)
    return f


def newton_cells(row):
    """The Newton columns (mean, max) of a table row, blank for the linearised step."""
    cells = "" if row["newton_mean"] is None else f"{row['newton_mean']:7.2f} {row['newton_max']:4d}"
    return f"{cells:>12s}"


def stiffchain_energy(integrator, dt, **options):
    """The shipped ``stiffchain`` over 2 s: a row with the largest total energy above its
    start and the end's (J), the wall time and the Newton iterations per step."""
    sim = ms.load_scene("stiffchain").simulation(integrator, dt=dt, **options)
    e0 = sim.energy()["total"]
    top, start = -np.inf, time.perf_counter()
    for _ in range(int(round(2.0 / dt))):
        sim.step()
        top = max(top, sim.energy()["total"] - e0)
    newton = sim.newton_iterations
    row = {"dt": dt, "integrator": integrator, **options, "max_gain_J": top, "end_J": sim.energy()["total"] - e0,
           "wall_s": time.perf_counter() - start, "newton_mean": float(np.mean(newton)) if newton else None,
           "newton_max": max(newton) if newton else None, "not_converged": sim.cg_failures}
    sim.close()
    return row


def energy_table():
    rows = [stiffchain_energy(integrator, dt) for dt in (0.01, 0.002) for integrator in ("implicit", *NEWTON)]
    print("stiffchain, 2 s: energy above the start (J)")
    print(f"{'dt':>6s}  {'integrator':15s} {'max gain':>10s} {'end':>10s} {'wall s':>7s} {'Newton':>7s} {'max':>4s} "
          f"{'fail':>4s}")
    for r in rows:
        print(f"{r['dt']:6g}  {r['integrator']:15s} {r['max_gain_J']:10.3g} {r['end_J']:10.3g} {r['wall_s']:7.2f} "
              f"{newton_cells(r)} {r['not_converged']:4d}")
    return rows


def step_residual(integrator, **options):
    """One step from a stretched, moving ``stiffchain`` state at dt 0.01: a row with the
    backward-Euler equations' residual ||M (v1 - v0) - dt f(x1, v1)|| / ||dt f(x0, v0)||
    on the free particles and the Newton iterations."""
    model = ms.load_scene("stiffchain").model()
    rng = np.random.default_rng(4)
    x = model.positions * 1.02 + rng.normal(scale=1e-3, size=model.positions.shape)
    v = rng.normal(scale=0.5, size=x.shape)
    x[model.fixed], v[model.fixed] = model.positions[model.fixed], 0.0
    dt, free = 0.01, model.free_mask()
    sim = ms.Simulation(model, integrator, dt=dt, **options).set_state(x, v)
    sim.step()
    residual = model.masses[:, None] * (sim.velocities - v) - dt * forces(model, sim.positions, sim.velocities)
    scale = np.linalg.norm((dt * forces(model, x, v))[free])
    row = {"integrator": integrator, **options, "relative_residual": float(np.linalg.norm(residual[free]) / scale),
           "newton_iterations": sim.solver_stats.newton_iterations}
    sim.close()
    return row


def residual_table():
    rows = [step_residual("implicit"), step_residual("backward-euler"),
            step_residual("backward-euler", newton_tol=1e-8)]
    print("\none step of a stretched, moving stiffchain (dt 0.01): backward-Euler residual / ||dt f||")
    for r in rows:
        print(f"  {r['integrator']:15s} newton_tol {r.get('newton_tol', 'default')!s:8s} {r['relative_residual']:.3g}"
              + ("" if r["newton_iterations"] is None else f"  ({r['newton_iterations']} Newton iterations)"))
    return rows


def order_table():
    scene = ms.load_scene("chain")
    duration, counts = 0.25, (500, 1000, 2000, 4000)
    reference = scene.simulation("rk4", dt=duration / 40000).step(40000).positions
    rows = []
    for integrator in NEWTON:
        errors = []
        for n in counts:
            sim = scene.simulation(integrator, dt=duration / n, newton_tol=1e-10, cg_tol=1e-12, newton_max_iter=100)
            start = time.perf_counter()
            sim.step(n)
            errors.append(float(np.abs(sim.positions - reference).max()))
            rows.append({"integrator": integrator, "dt": duration / n, "error_m": errors[-1],
                         "wall_s": time.perf_counter() - start})
            sim.close()
        orders = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
        for row, order in zip(rows[-len(counts) + 1:], orders):
            row["order"] = float(order)
    print("\nchain, 0.25 s, against RK4 at dt 6.25e-6: largest position error (m)")
    for r in rows:
        print(f"  {r['integrator']:15s} dt {r['dt']:.3g}  error {r['error_m']:.3g}" +
              (f"  order {r['order']:.3f}" if "order" in r else ""))
    return rows


def terminal_table():
    m, c, g, wind = 0.2, 0.5, np.array([0.0, 0.0, -9.81]), np.array([1.0, -0.5, 0.0])
    model = ms.Model([[0.0, 0.0, 0.0]], np.zeros((0, 2), int), masses=m, gravity=g, drag=c, wind=wind)
    terminal = m * g / c + wind
    rows = []
    for integrator in ("implicit", *NEWTON):
        sim = ms.Simulation(model, integrator, dt=0.05).step(600)
        rows.append({"integrator": integrator,
                     "relative_error": float(np.linalg.norm(sim.velocities[0] - terminal) / np.linalg.norm(terminal))})
        sim.close()
    print("\nterminal velocity with drag and wind after 30 s (dt 0.05, default tolerances): relative error")
    for r in rows:
        print(f"  {r['integrator']:15s} {r['relative_error']:.3g}")
    return rows


def interleaved(sims, steps):
    """{key: wall times (s) of ``steps`` steps} of the simulations ``sims`` ({key: Simulation}),
    after one untimed step each (it compiles), taken in turn: the machine's load falls on all alike."""
    for sim in sims.values():
        sim.step(1)
    times = {key: [] for key in sims}
    for _ in range(steps):
        for key, sim in sims.items():
            start = time.perf_counter()
            sim.step(1)
            times[key].append(time.perf_counter() - start)
    return times


def cloth_table(resolution, steps):
    scene = ms.load_scene("cloth").with_params(resolution=resolution, stiffness=1e4)
    sims = {name: scene.simulation(name, dt=1 / 60, preconditioner="multigrid") for name in ("implicit", *NEWTON)}
    times = interleaved(sims, steps)
    base = statistics.median(times["implicit"])
    rows = []
    for name, sim in sims.items():
        newton = sim.newton_iterations[1:]
        rows.append({"integrator": name, "resolution": resolution, "steps": steps,
                     "median_ms": 1e3 * statistics.median(times[name]),
                     "ratio_to_implicit": statistics.median(times[name]) / base,
                     "newton_mean": float(np.mean(newton)) if newton else None,
                     "newton_max": max(newton) if newton else None,
                     "cg_per_step": float(np.mean(sim.cg_iterations[1:])), "not_converged": sim.cg_failures})
        sim.close()
    print(f"\ncloth {resolution} x {resolution}, dt 1/60, ks 1e4, multigrid, {steps} steps after the first")
    print(f"  {'integrator':15s} {'ms/step':>9s} {'ratio':>6s} {'Newton':>7s} {'max':>4s} {'CG/step':>8s} {'fail':>4s}")
    for r in rows:
        print(f"  {r['integrator']:15s} {r['median_ms']:9.1f} {r['ratio_to_implicit']:6.2f} {newton_cells(r)} "
              f"{r['cg_per_step']:8.1f} {r['not_converged']:4d}")
    return rows


def damping_table():
    cases = [(kd, 1 / 60, 20) for kd in (2.0, 20.0, 200.0, 2000.0)] + [(1e9, 1.0, 3)]
    rows = []
    for integrator in NEWTON:
        for kd, dt, steps in cases:
            sim = ms.load_scene("cloth").with_settings([f"damping={kd:g}"]).simulation(integrator, dt=dt)
            newton, cg, missed, outcome, cpu = [], [], 0, "ran", 0.0
            try:
                for _ in range(steps):
                    start = time.process_time()
                    sim.step(1)
                    cpu += time.process_time() - start
                    newton.append(sim.solver_stats.newton_iterations)
                    cg.append(sim.solver_stats.iterations)
                    missed += not sim.solver_stats.converged
            except ms.DivergenceError as error:
                outcome = str(error).split(": ", 1)[-1].split(";")[0]
            rows.append({"integrator": integrator, "damping": kd, "dt": dt, "steps": len(newton),
                         "newton_mean": float(np.mean(newton)) if newton else None,
                         "newton_max": max(newton) if newton else None, "missed": missed,
                         "cg_per_step": float(np.mean(cg)) if cg else None,
                         "cpu_ms_per_step": 1e3 * cpu / len(newton) if newton else None,
                         "kinetic_J": sim.energy()["kinetic"], "outcome": outcome})
            sim.close()
    print("\ncloth 32 x 32, spring damping raised: Newton iterations per step, steps that missed newton_tol, "
          "CG iterations and CPU ms per step (the first step's compile included)")
    print(f"  {'integrator':15s} {'damping':>8s} {'dt':>7s} {'steps':>5s} {'Newton':>7s} {'max':>4s} {'missed':>6s}"
          f" {'CG/step':>8s} {'CPU ms':>8s} {'kinetic J':>10s}  outcome")
    for r in rows:
        measured = (f"{r['cg_per_step']:8.1f} {r['cpu_ms_per_step']:8.1f}" if r["steps"] else f"{'':8s} {'':8s}")
        print(f"  {r['integrator']:15s} {r['damping']:8.3g} {r['dt']:7.3g} {r['steps']:5d} {newton_cells(r)} "
              f"{r['missed']:6d} {measured} {r['kinetic_J']:10.3g}  {r['outcome']}")
    return rows


def tolerance_table(resolution, steps):
    scene = ms.load_scene("cloth").with_params(resolution=resolution, stiffness=1e4)

    def simulation(integrator, dt=1 / 60, **options):
        return scene.simulation(integrator, dt=dt, preconditioner="multigrid", **options)

    runs = {("implicit", None): simulation("implicit")}
    for integrator in NEWTON:
        for tol in TOLERANCES:
            runs[integrator, tol] = simulation(integrator, newton_tol=tol)
    times = interleaved(runs, steps)
    tight = {}  # integrator -> (end positions, Newton iterations a step) at newton_tol TIGHT
    for integrator in NEWTON:
        sim = simulation(integrator, newton_tol=TIGHT).step(steps + 1)
        tight[integrator] = (sim.positions.copy(), float(np.mean(sim.newton_iterations)))
        sim.close()
    sim = simulation("backward-euler", dt=1 / 120, newton_tol=TIGHT).step(2 * (steps + 1))
    truncation = float(np.abs(sim.positions - tight["backward-euler"][0]).max())
    sim.close()
    base = statistics.median(times["implicit", None])
    rows = []
    for (name, tol), sim in runs.items():
        newton = sim.newton_iterations[1:]
        reference = tight["backward-euler" if tol is None else name][0]
        rows.append({"integrator": name, "newton_tol": tol, "resolution": resolution, "steps": steps,
                     "median_ms": 1e3 * statistics.median(times[name, tol]),
                     "ratio_to_implicit": statistics.median(times[name, tol]) / base,
                     "newton_mean": float(np.mean(newton)) if newton else None,
                     "newton_max": max(newton) if newton else None,
                     "distance_to_tight_m": float(np.abs(sim.positions - reference).max()),
                     "stiffchain_residual": None if tol is None or name != "backward-euler" else
                     step_residual(name, newton_tol=tol)["relative_residual"],
                     "stiffchain_max_gain_J": stiffchain_energy(name, 1 / 60, newton_tol=tol)["max_gain_J"]
                     if tol and name == "backward-euler" else None})
        sim.close()
    print(f"\ncloth {resolution} x {resolution}, dt 1/60, ks 1e4, multigrid, {steps} steps after the first: "
          f"what newton_tol buys")
    for name, (_, newton) in tight.items():
        print(f"  {name} at newton_tol {TIGHT:g}: {newton:.1f} Newton iterations a step")
    print(f"  backward Euler at {TIGHT:g}, dt 1/60 against dt 1/120 (the time step's error, for scale): "
          f"{truncation:.2e} m")
    print(f"  {'integrator':15s} {'newton_tol':>10s} {'ms/step':>9s} {'ratio':>6s} {'Newton':>7s} {'max':>4s} "
          f"{'distance m':>10s} {'chain residual':>14s} {'chain gain J':>12s}")
    for r in rows:
        tol = "" if r["newton_tol"] is None else f"{r['newton_tol']:g}"
        chain = "" if r["stiffchain_residual"] is None else f"{r['stiffchain_residual']:.2g}"
        gain = "" if r["stiffchain_max_gain_J"] is None else f"{r['stiffchain_max_gain_J']:.2g}"
        print(f"  {r['integrator']:15s} {tol:>10s} {r['median_ms']:9.1f} {r['ratio_to_implicit']:6.2f} "
              f"{newton_cells(r)} {r['distance_to_tight_m']:10.2e} {chain:>14s} {gain:>12s}")
    print("  (distance: largest of the end positions from the same integrator's run at newton_tol "
          f"{TIGHT:g}, the linearised step's from backward Euler's; chain residual: table 2's step; chain gain: "
          "stiffchain's largest energy above its start over 2 s at dt 1/60)")
    return {"rows": rows, "tight_newton_tol": TIGHT, "tight_newton_mean": {k: v[1] for k, v in tight.items()},
            "tight_to_half_dt_m": truncation}


def curvature_table(resolution, steps):
    from scipy.sparse.linalg import eigsh

    scene = ms.load_scene("cloth").with_params(resolution=resolution, stiffness=1e4)
    model, h = scene.model(), 1 / 60
    sim = scene.simulation("backward-euler", dt=h, preconditioner="multigrid")
    states = []
    for _ in range(steps):
        states.append((sim.positions.copy(), sim.velocities.copy()))
        sim.step()
    worst = int(np.argmax(sim.newton_iterations))
    iterations = sim.newton_iterations[worst]
    sim.close()
    x, v = states[worst]
    sim = ms.Simulation(model, "backward-euler", dt=h, preconditioner="multigrid", newton_tol=1e-9,
                        newton_max_iter=400, cg_tol=1e-10).set_state(x, v)
    sim.step()
    stats, end = sim.solver_stats, sim.positions.copy()
    sim.close()
    mass = float(np.mean(model.masses[model.free_mask()]))
    points = []
    for name, at in (("first iterate", x + h * v), ("last iterate", end)):
        # M - h D - h^2 K on the free degrees of freedom: Eq. 15's A, with the true K and with the fix's
        true, fixed = (peers.assemble_system(model, at, np.zeros_like(at), h, fix)[0].tocsc() for fix in (False, True))
        i, j = model.springs[:, 0], model.springs[:, 1]
        compressed = np.linalg.norm(at[j] - at[i], axis=1) < model.rest_lengths
        true_low = np.sort(eigsh(true, k=4, sigma=-10 * mass, return_eigenvectors=False)) / mass
        fixed_low = np.sort(eigsh(fixed, k=2, sigma=0.0, return_eigenvectors=False)) / mass
        mu = float(np.min(eigsh(true, k=2, M=fixed, sigma=-0.5, return_eigenvectors=False)))
        points.append({"point": name, "compressed_fraction": float(np.mean(compressed)),
                       "true_smallest_over_mass": true_low.tolist(), "fixed_smallest_over_mass": fixed_low.tolist(),
                       "smallest_mu": mu, "rate": 1.0 - mu})
    print(f"\ncloth {resolution} x {resolution}, dt 1/60, ks 1e4: step {worst} took {iterations} Newton iterations "
          f"at default settings; at newton_tol 1e-9 it takes {stats.newton_iterations} "
          f"(residual {stats.newton_residual:.1e} of its first)")
    print(f"  {'at the':15s} {'compressed':>10s} {'true H / m, smallest':>30s} {'fixed H / m':>14s} {'mu':>8s} "
          f"{'1 - mu':>7s}")
    for r in points:
        true_low = " ".join(f"{value:6.3f}" for value in r["true_smallest_over_mass"])
        fixed_low = " ".join(f"{value:6.3f}" for value in r["fixed_smallest_over_mass"])
        print(f"  {r['point']:15s} {r['compressed_fraction']:10.2f} {true_low:>30s} {fixed_low:>14s} "
              f"{r['smallest_mu']:8.4f} {r['rate']:7.4f}")
    return {"resolution": resolution, "step": worst, "default_newton_iterations": iterations,
            "tight_newton_iterations": stats.newton_iterations, "tight_residual": stats.newton_residual,
            "points": points}


def main(argv=None):
    args = parse_args(argv)
    result = {}
    for table in args.tables:
        if table in ("cloth", "tolerance", "curvature"):
            result[table] = globals()[f"{table}_table"](args.resolution, args.steps)
        else:
            result[table] = globals()[f"{table}_table"]()
    write_json(args.json, result)
    print(f"\nwrote {args.json}")


if __name__ == "__main__":
    main()
