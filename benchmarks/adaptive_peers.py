"""Error-controlled runs of massspring against SciPy's and SUNDIALS' adaptive ODE solvers.

Each problem (a built-in scene, to the study's end time T =
``analysis.study.default_duration``) is solved by

* massspring, ``Simulation(model, integrator=name, dt=scene's dt, tol=tol, horizon=T)``
  and ``sim.advance(T)``, for each integrator and each tolerance of ``--tols``;
* SciPy's ``solve_ivp`` (Radau, BDF, LSODA) on the first-order system y' = (v, f(x, v) / m)
  over the free particles' positions and velocities. Its right-hand side is
  ``benchmarks/peers.spring_forces``; its Jacobian is read off ``peers.assemble_system``
  (Eq. 15, without the definiteness fix: M + h D + h^2 K, with K = -df/dx and D = -df/dv,
  so two assemblies, h = 1 and h = -1, give K and D exactly). Eq. 15 leaves out the damping
  force's change with the spring's direction (kd ((v_j - v_i) . n) n through n), so this is
  the Jacobian up to that term (2e-4 of its largest entry on the chain at a perturbed state):
  the implicit peers' Newton iterations converge on it as on any approximate Jacobian,
  their accuracy is their error estimate's. Radau and BDF take it as a
  sparse matrix (``jac``); LSODA takes no sparse matrix, so it gets the same Jacobian
  packed as a band (``lband``/``uband``; the unknowns are ordered per particle, x then v,
  so the band is as narrow as the mesh numbering allows);
* SUNDIALS CVODE (BDF, orders 1-5) through scikit-sundae (``sksundae``), with its sparse
  direct linear solver (SuperLU_MT, one thread) on the same sparse Jacobian (``jacfn``);
  skipped, with the reason in the JSON, if ``sksundae`` cannot be imported or fails a
  one-line test problem (scikit-sundae 1.2.0 installed from a wheel and ran here).

A peer's tolerance ``tau`` of ``--peer-tols`` is rtol = tau and atol = tau times the
scale of each component (positions: the scene size L, velocities: L / T), so that one
ladder covers the same range of end errors as massspring's ``tol``.

Errors. The study's measure: RMS over the moving particles of |x(T) - x_ref(T)|, over
L (``engine.adaptive.scene_size``). The common reference is massspring's RK4 at a fixed
dt (``analysis.reference.rk4``, float64), the stability limit's top rung (``ladder_tops``)
over ``--ref-divisions``, checked against RK4 at half that dt (the JSON's
``reference.change``; the finer one is the reference). On the spring scene every run is
also scored against the exact solution (``error_exact``).

Time. CPU time of the solve alone (``time.process_time``: every thread of the process;
Taichi's are counted), the median of ``--repeats`` runs, after one untimed warm-up run per
(problem, method) that compiles massspring's kernels (and warms SciPy's caches). Building
the Simulation or the solver object is not timed. A method stops going down the ladder
when its next run would likely pass ``--budget`` CPU seconds.

Matched error. For each peer curve (CPU time against error, log-log, points sorted by
error), the CPU time it would take at each massspring run's error is interpolated
(never extrapolated: outside the curve's range it is left out); the ratio peer /
massspring > 1 means massspring is faster at that error.

Run: python benchmarks/adaptive_peers.py [--problems spring chain cloth16 cloth32]
[--integrators ...] [--tols ...] [--peer-tols ...] [--repeats N] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import statistics
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import output  # noqa: E402
from peers import assemble_system, spring_forces  # noqa: E402

import massspring as ms  # noqa: E402
from massspring.analysis import reference  # noqa: E402
from massspring.analysis.study import default_duration, ladder_tops  # noqa: E402
from massspring.engine.adaptive import scene_size  # noqa: E402
from massspring.scene.spec import load_scene  # noqa: E402

INTEGRATORS = ["bdf2", "midpoint", "rk4", "backward-euler"]
SCIPY_METHODS = ["Radau", "BDF", "LSODA"]
TOLS = [1e-2, 1e-3, 1e-4, 1e-5, 1e-6]
PEER_TOLS = [1e-1, 1e-2, 1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-8]
PROBLEMS = ["spring", "chain", "cloth16"]
ORDER = {"backward-euler": 1, "bdf2": 2, "midpoint": 2, "rk4": 4}  # for the budget's guess of the next run


def problem(name):
    """(scene, model) of a problem name: a scene, or cloth<resolution>."""
    if name.startswith("cloth") and name[5:].isdigit():
        scene = load_scene("cloth").with_params(resolution=int(name[5:]))
    else:
        scene = load_scene(name)
    model = scene.model()
    if model.has_drag or model.has_colliders or model.has_moving_pins or model.controls is not None:
        raise SystemExit(f"{name}: the peers' right-hand side has springs and gravity only")
    return scene, model


class FirstOrderSystem:
    """y' = F(y) over the free particles, unknowns ordered per particle (x, then v)."""

    def __init__(self, model):
        self.model = model
        self.free = model.free_mask()
        self.nf = int(self.free.sum())
        self.n = 6 * self.nf
        self.x = model.positions.astype(np.float64).copy()
        self.v = np.zeros_like(self.x)
        self.minv = 1.0 / model.masses[self.free]
        block = np.arange(self.n).reshape(self.nf, 2, 3)  # interleaved index -> (particle, x/v, k)
        # block layout [x_free; v_free] -> interleaved layout
        self.perm = np.concatenate([block[:, 0].ravel(), block[:, 1].ravel()])
        self.mass3 = np.repeat(model.masses[self.free], 3)

    def y0(self):
        y = np.empty((self.nf, 6))
        y[:, :3] = self.model.positions[self.free]
        y[:, 3:] = self.model.velocities[self.free]
        return y.ravel()

    def scale(self, size, horizon):
        s = np.empty((self.nf, 6))
        s[:, :3], s[:, 3:] = size, size / horizon
        return s.ravel()

    def state(self, y):
        y = y.reshape(self.nf, 6)
        self.x[self.free] = y[:, :3]
        self.v[self.free] = y[:, 3:]
        return self.x, self.v

    def rhs(self, t, y):
        x, v = self.state(y)
        out = np.empty((self.nf, 6))
        out[:, :3] = v[self.free]
        out[:, 3:] = spring_forces(self.model, x, v)[self.free] * self.minv[:, None]
        return out.ravel()

    def jac_entries(self, t, y):
        """(rows, cols, values) of dF/dy, from Eq. 15 assembled at h = 1 and h = -1 (duplicates summed by the caller)."""
        import scipy.sparse as sp

        x, v = self.state(y)
        plus = assemble_system(self.model, x, v, 1.0, definiteness_fix=False)[0]
        minus = assemble_system(self.model, x, v, -1.0, definiteness_fix=False)[0]
        mass = sp.diags(self.mass3)
        stiffness = (plus + minus) * 0.5 - mass  # K = -df/dx
        damping = (plus - minus) * 0.5  # D = -df/dv
        minv = sp.diags(1.0 / self.mass3)
        eye = sp.identity(3 * self.nf, format="csr")
        coo = sp.bmat([[None, eye], [-(minv @ stiffness), -(minv @ damping)]], format="coo")
        return self.perm[coo.row], self.perm[coo.col], coo.data

    def jac(self, t, y):
        """Sparse (CSC) dF/dy."""
        import scipy.sparse as sp

        rows, cols, values = self.jac_entries(t, y)
        return sp.csc_matrix((values, (rows, cols)), shape=(self.n, self.n))

    def pattern(self):
        """CSC sparsity pattern (ones, indices sorted) of the Jacobian at any state: the union of
        the initial state's and a perturbed one's (an entry can vanish at a symmetric state)."""
        y0 = self.y0()
        noise = 1e-3 * np.random.default_rng(0).standard_normal(self.n)
        j = (abs(self.jac(0.0, y0)) + abs(self.jac(0.0, y0 + noise))).tocsc()
        j.sum_duplicates()
        j.sort_indices()
        j.data[:] = 1.0
        return j

    def bands(self):
        j = self.pattern().tocoo()
        return int(np.max(j.row - j.col)), int(np.max(j.col - j.row))

    def packed_jac(self, lband, uband):
        def jac(t, y):
            rows, cols, values = self.jac_entries(t, y)
            out = np.zeros((lband + uband + 1, self.n))
            np.add.at(out, (uband + rows - cols, cols), values)
            return out
        return jac

    def positions(self, y):
        x = self.model.positions.astype(np.float64).copy()
        x[self.free] = y.reshape(self.nf, 6)[:, :3]
        return x


def error_of(x, ref, moving, size):
    d = x[moving] - ref[moving]
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1)))) / size


def timed(function, repeats):
    """(result of the last call, median CPU s, all CPU s) of ``function`` called ``repeats`` times."""
    times, result = [], None
    for _ in range(repeats):
        result, cpu = function()
        times.append(cpu)
    return result, statistics.median(times), times


def massspring_run(model, scene, integrator, tol, horizon):
    def once():
        sim = ms.Simulation(model, integrator=integrator, dt=scene.default_dt(integrator), tol=tol, horizon=horizon)
        start = time.process_time()
        sim.advance(horizon)
        cpu = time.process_time() - start
        x, stats = sim.positions, sim.control_stats()
        sim.close()
        return (x, stats), cpu
    return once


def scipy_run(system, method, tau, horizon, size, bands):
    from scipy.integrate import solve_ivp

    atol = tau * system.scale(size, horizon)
    if method == "LSODA":
        lband, uband = bands
        options = dict(jac=system.packed_jac(lband, uband), lband=lband, uband=uband)
    else:
        options = dict(jac=system.jac)

    def once():
        start = time.process_time()
        sol = solve_ivp(system.rhs, (0.0, horizon), system.y0(), method=method, rtol=tau, atol=atol,
                        t_eval=[horizon], **options)
        cpu = time.process_time() - start
        if not sol.success:
            raise RuntimeError(sol.message)
        info = {"steps": None, "nfev": int(sol.nfev), "njev": int(sol.njev), "nlu": int(sol.nlu)}
        return (system.positions(sol.y[:, -1]), info), cpu
    return once


def cvode_run(system, tau, horizon, size, pattern):
    from sksundae.cvode import CVODE

    atol = tau * system.scale(size, horizon)
    n = system.n
    keys = np.repeat(np.arange(n), np.diff(pattern.indptr)) * n + pattern.indices  # CSC order: column, then row

    def rhsfn(t, y, yp):
        yp[:] = system.rhs(t, y)

    def jacfn(t, y, yp, jj):
        rows, cols, values = system.jac_entries(t, y)
        jj[:] = 0.0
        np.add.at(jj, np.searchsorted(keys, cols * n + rows), values)

    def once():
        with warnings.catch_warnings():  # "custom sparse Jacobian approximation ignored": jacfn is given
            warnings.simplefilter("ignore", UserWarning)
            solver = CVODE(rhsfn, method="BDF", rtol=tau, atol=atol, linsolver="sparse", sparsity=pattern,
                           jacfn=jacfn, max_num_steps=10**7)
        start = time.process_time()
        sol = solver.solve(np.array([0.0, horizon]), system.y0())
        cpu = time.process_time() - start
        if not sol.success:
            raise RuntimeError(sol.message)
        info = {"steps": None, "nfev": int(sol.nfev), "njev": int(sol.njev)}  # the result has no step count
        return (system.positions(np.asarray(sol.y)[-1]), info), cpu
    return once


def cvode_available():
    try:
        import sksundae  # noqa: F401
        from sksundae.cvode import CVODE

        solver = CVODE(lambda t, y, yp: yp.__setitem__(slice(None), -y), rtol=1e-8, atol=1e-10)
        sol = solver.solve(np.array([0.0, 1.0]), np.array([1.0]))
        if not sol.success or abs(float(np.asarray(sol.y)[-1, 0]) - math.exp(-1)) > 1e-6:
            return False, f"sksundae ran but missed y' = -y: {sol.message}"
        return True, f"scikit-sundae {sksundae.__version__}"
    except Exception as exc:  # noqa: BLE001 - any failure to import or run: record it, skip CVODE
        return False, f"{type(exc).__name__}: {exc}"


def make_reference(scene, model, horizon, divisions):
    top = ladder_tops(scene, model, ["rk4"], horizon)["rk4"] / divisions
    dt = horizon / math.ceil(horizon / top - 1e-9)
    start = time.process_time()
    coarse = reference.rk4(model, [horizon], dt, use_cache=False)
    fine = reference.rk4(model, [horizon], dt / 2, use_cache=False)
    cpu = time.process_time() - start
    return fine, dt / 2, coarse, cpu


def warm_up(run):
    """One untimed run (compiles Taichi's kernels, warms SciPy's); a failure shows again in the ladder."""
    try:
        run()
    except Exception:  # noqa: BLE001
        pass


def ladder(label, values, run, budget, order, repeats, record):
    """Run ``run(value)`` down ``values`` (each loosest first) until the next would pass ``budget``."""
    previous = None
    for value in values:
        try:
            result, cpu, cpus = timed(run(value), repeats)
        except Exception as exc:  # noqa: BLE001 - a failed solve is recorded; the ladder goes on
            record(value, None, None, None, f"failed: {type(exc).__name__}: {exc}")
            print(f"  {label:16s} {value:8.0e}  failed: {exc}", flush=True)
            continue
        record(value, result, cpu, cpus, "ok")
        growth = (cpu / previous) if previous and previous > 0 else 10 ** (1 / order)
        previous = cpu
        if cpu * max(growth, 1.2) > budget:
            print(f"  {label:16s} stops after {value:.0e} (next run over the budget)", flush=True)
            return


def measure(name, args, cvode_ok):
    scene, model = problem(name)
    horizon = default_duration(scene)
    size = scene_size(model)
    moving = model.free_mask()
    system = FirstOrderSystem(model)
    print(f"{name}: {model.n_particles} particles, {model.n_springs} springs, {system.n} unknowns, "
          f"T = {horizon:g} s, L = {size:g} m", flush=True)
    ref, ref_dt, coarse, ref_cpu = make_reference(scene, model, horizon, args.ref_divisions)
    x_ref = ref.positions[-1]
    exact = reference.exact_spring(model, [horizon])
    entry = {"problem": name, "scene": scene.name, "params": {k: v for k, v in dict(scene.params).items()
                                                                if isinstance(v, (int, float, str))},
             "particles": model.n_particles, "springs": model.n_springs, "unknowns": system.n,
             "horizon_s": horizon, "scene_size_m": size,
             "reference": {"method": "massspring rk4, fixed dt, float64", "dt_s": ref_dt,
                           "change": error_of(coarse.positions[-1], x_ref, moving, size), "cpu_s": ref_cpu},
             "runs": []}
    if exact is not None:
        entry["reference"]["error_exact"] = error_of(x_ref, exact.positions[-1], moving, size)
    print(f"  reference: RK4 dt {ref_dt:.3g} s, change on halving {entry['reference']['change']:.2e}"
          + (f", against exact {entry['reference']['error_exact']:.2e}" if exact is not None else ""), flush=True)

    def recorder(family, method, kind):
        def record(value, result, cpu, cpus, status):
            row = {"family": family, "method": method, kind: value, "status": status}
            if result is not None:
                x, info = result
                row.update(error=error_of(x, x_ref, moving, size), cpu_s=cpu, cpu_all_s=cpus)
                if exact is not None:
                    row["error_exact"] = error_of(x, exact.positions[-1], moving, size)
                if family == "massspring":
                    row.update(steps=int(info["accepted"]) if "accepted" in info else None, control=_plain(info))
                else:
                    row.update(info)
                print(f"  {family + ' ' + method:26s} {value:8.0e}  error {row['error']:9.2e}  cpu {cpu:9.4f} s"
                      + (f"  steps {row['steps']}" if row.get("steps") else ""), flush=True)
            entry["runs"].append(row)
        return record

    for integrator in args.integrators:
        warm_up(massspring_run(model, scene, integrator, args.tols[0], horizon))
        ladder(integrator, args.tols, lambda tol, i=integrator: massspring_run(model, scene, i, tol, horizon),
               args.budget, ORDER.get(integrator, 2), args.repeats, recorder("massspring", integrator, "tol"))
    bands = system.bands()
    for method in args.methods:
        warm_up(scipy_run(system, method, args.peer_tols[0], horizon, size, bands))
        ladder(method, args.peer_tols, lambda tau, m=method: scipy_run(system, m, tau, horizon, size, bands),
               args.budget, 3, args.repeats, recorder("scipy", method, "rtol"))
    if cvode_ok and not args.no_cvode:
        pattern = system.pattern()
        warm_up(cvode_run(system, args.peer_tols[0], horizon, size, pattern))
        ladder("CVODE", args.peer_tols, lambda tau: cvode_run(system, tau, horizon, size, pattern),
               args.budget, 3, args.repeats, recorder("cvode", "CVODE", "rtol"))
    entry["matched"] = matched(entry["runs"])
    return entry


def _plain(info):
    return {k: (float(v) if isinstance(v, float) else v) for k, v in dict(info).items()
            if isinstance(v, (int, float, str, type(None)))}


def matched(runs):
    """For each massspring run, each peer's interpolated CPU time at its error, and the ratio."""
    ok = [r for r in runs if r["status"] == "ok" and r["error"] > 0]
    peers = sorted({(r["family"], r["method"]) for r in ok if r["family"] != "massspring"})
    rows = []
    for run in (r for r in ok if r["family"] == "massspring"):
        row = {"integrator": run["method"], "tol": run["tol"], "error": run["error"], "cpu_s": run["cpu_s"],
               "peers": {}}
        for family, method in peers:
            curve = sorted((r["error"], r["cpu_s"]) for r in ok if (r["family"], r["method"]) == (family, method))
            errors = np.log([e for e, _ in curve])
            cpus = np.log([max(c, 1e-9) for _, c in curve])
            at = math.log(run["error"])
            if len(curve) < 2 or not errors[0] <= at <= errors[-1]:
                continue
            cpu = float(np.exp(np.interp(at, errors, cpus)))
            row["peers"][method] = {"cpu_s": cpu, "ratio": cpu / run["cpu_s"]}
        rows.append(row)
    return rows


def print_matched(entry):
    methods = sorted({m for row in entry["matched"] for m in row["peers"]})
    print(f"\n{entry['problem']}: CPU time of each peer at massspring's error, over massspring's (> 1: massspring faster)")
    print(f"  {'integrator':15s} {'tol':>7s} {'error':>9s} {'cpu s':>9s} " + " ".join(f"{m:>8s}" for m in methods))
    for row in entry["matched"]:
        cells = [f"{row['peers'][m]['ratio']:8.2f}" if m in row["peers"] else f"{'-':>8s}" for m in methods]
        print(f"  {row['integrator']:15s} {row['tol']:7.0e} {row['error']:9.2e} {row['cpu_s']:9.4f} " + " ".join(cells))


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--problems", nargs="+", default=PROBLEMS, help="scenes; cloth<N> is the cloth at resolution N")
    p.add_argument("--integrators", nargs="+", default=INTEGRATORS)
    p.add_argument("--methods", nargs="+", default=SCIPY_METHODS, help="solve_ivp methods")
    p.add_argument("--no-cvode", action="store_true", help="skip CVODE")
    p.add_argument("--tols", nargs="+", type=float, default=TOLS, help="massspring's tol ladder, loosest first")
    p.add_argument("--peer-tols", nargs="+", type=float, default=PEER_TOLS,
                   help="the peers' rtol ladder (atol: the same times L and L / T), loosest first")
    p.add_argument("--repeats", type=int, default=1, help="timed runs per point (median)")
    p.add_argument("--budget", type=float, default=30.0, help="CPU s a method's next run may take")
    p.add_argument("--ref-divisions", type=int, default=64, help="RK4 reference dt: its stability top over this")
    output.add_json(p, "adaptive_peers")
    args = p.parse_args()

    cvode_ok, cvode_note = cvode_available()
    print(f"CVODE: {'available' if cvode_ok else 'skipped'} ({cvode_note})", flush=True)
    results = {"command": "python benchmarks/adaptive_peers.py " + " ".join(sys.argv[1:]),
               "machine": {"python": platform.python_version(), "processor": platform.processor() or platform.machine()},
               "cvode": {"available": cvode_ok, "note": cvode_note}, "problems": []}
    for name in args.problems:
        results["problems"].append(measure(name, args, cvode_ok))
    for entry in results["problems"]:
        print_matched(entry)
    path = Path(args.json)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(results, indent=1) + "\n")
    print(f"\nwrote {path}")


if __name__ == "__main__":
    main()
