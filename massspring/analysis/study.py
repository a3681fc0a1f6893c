"""Work-precision study: error against run time for every integrator, dt and CG tolerance.

``run_study`` runs a scene with each integrator over a ladder of dt values (a
factor of 2 apart), the implicit one also at several CG tolerances and with each
given preconditioner, all to the same end time, and measures each run against a reference solution
(``analysis.reference``: exact for one spring, else RK4 checked by halving its dt).

Measures of a run (all dimensionless unless stated):

* ``error``: RMS over the moving particles of |x - x_ref| at the end time, divided by
  the scene's size (the largest side of the bounding box of the initial positions;
  1 m if that is 0).
* ``error_over_time``: the same RMS taken over all particles and all save instants.
* ``energy_error``: |E(T) - E_ref(T)| / E_scale, E the total energy (``Model.energy``)
  and E_scale the largest kinetic + spring energy of the reference at any save
  instant or at t = 0 (gravity potential has an arbitrary zero, so it is no scale).
* ``wall_s``: seconds of stepping alone (``Simulation.step``): after one warm-up run
  per integrator (compilation), the minimum over timed runs. The first timed run is the
  measured one (it steps between save instants; readbacks are not timed); more runs,
  each after one untimed step on its fresh Simulation, follow in rounds, interleaved:
  each round times every run once more, in the study's order, while fewer than
  ``repeats`` were timed and their total is under ``time_budget`` seconds, so that a
  shared machine's load, which drifts over minutes, falls on every run alike.
* ``steps``, ``cg_iterations`` (total over the run; 0 for the explicit integrators).
* ``diverged``: the run raised ``DivergenceError``, reached a non-finite state, or
  its RMS error at a save instant exceeded the scene's size (runaway). Its error,
  energy error and wall time are None, and it is left out of plots and fits.

``order``: the least-squares slope of log(error) against log(dt) over a line's
non-diverged runs (about 1 for all three Euler variants on smooth problems).

Error-controlled lines (``tols``): each integrator also run with ``Simulation(tol=t)``
for each t (its first step the top of its dt ladder, ``horizon`` the end time), landing
on every save instant; ``steps`` is then the steps it chose. They are in the table, the
files and the plot, and among the cheapest runs; no order is fitted to them.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field

import numpy as np

from massspring import solvers
from massspring.support import validate
from massspring.analysis import cluster, reference
from massspring.analysis.fits import TARGETS, cheapest, fit_orders
from massspring.analysis.hints import hints
from massspring.engine.adaptive import Tolerance, scene_size
from massspring.support.errors import DivergenceError
from massspring.integrators import INTEGRATORS, OPTIONS, REFERENCE, SMALLEST_DT, STUDIED, Integrator
from massspring.engine.simulation import Simulation

DEFAULT_CG_TOLS = OPTIONS["cg_tol"].sweep
DEFAULT_NEWTON_TOLS = OPTIONS["newton_tol"].sweep
DEFAULT_RUNGS = 7            # dt values per line: 2^6 = 64, about 2 decades
DEFAULT_DURATION_FRACTION = 0.1  # of the scene's duration (see default_duration)
MAX_REFERENCE_STEPS = 1e9  # steps of the RK4 reference at its starting dt
MAX_SAVES = 100
DEFAULT_REPEATS = 3
DEFAULT_TIME_BUDGET = 2.0    # s of timed runs per configuration before repeats stop
REFERENCE_RATIO = 1e-3       # RK4 halving change / smallest reported error must be below this
REFERENCE_HALVINGS = 4       # extra RK4 refinements tried before the check is reported failed
COLUMNS = ("integrator", "dt", "tol", "cg_tol", "newton_tol", "preconditioner", "error", "error_over_time",
           "energy_error", "wall_s", "steps", "cg_iterations", "diverged", "timed_runs", "status")


@dataclass
class Run:
    """One run of the study; see the module docstring for what each measure means."""

    integrator: str
    dt: float
    cg_tol: float | None
    preconditioner: str | None = None  # implicit runs: the one used ("auto" resolved)
    newton_tol: float | None = None  # Newton-solved runs: their newton_tol (cg_tol is then None)
    tol: float | None = None  # an error-controlled run's tol (``Simulation(tol=...)``; dt is then its first step)
    error: float | None = None
    error_over_time: float | None = None
    energy_error: float | None = None
    wall_s: float | None = None
    steps: int = 0
    cg_iterations: int = 0
    diverged: bool = False
    timed_runs: int = 0
    status: str = "ok"
    positions: np.ndarray | None = field(default=None, repr=False)   # (k, n, 3) at save instants
    velocities: np.ndarray | None = field(default=None, repr=False)  # (n, 3) at the end

    def row(self) -> dict:
        return {key: getattr(self, key) for key in COLUMNS}

    @property
    def line(self) -> str:
        """The plot line (and slope fit) this run belongs to."""
        if self.tol is not None:
            pre = f" ({self.preconditioner})" if self.preconditioner else ""
            return f"{self.integrator}{pre} error-controlled"
        if self.newton_tol is not None:
            return f"{self.integrator} ({self.preconditioner}) newton_tol={self.newton_tol:g}"
        if self.cg_tol is None:
            return self.integrator
        return f"{self.integrator} ({self.preconditioner}) cg_tol={self.cg_tol:g}"


@dataclass
class ReferenceCheck:
    """How the reference was obtained and whether it is accurate enough.

    For RK4: ``change`` is the largest of the end-time and over-time RMS differences
    (divided by the scene's size) between RK4 at ``dt`` and at ``2 dt``; ``passed`` when
    it is below ``ratio`` x ``smallest`` (the smallest error the study reports).
    """

    method: str
    dt: float | None = None
    change: float | None = None
    smallest: float | None = None
    ratio: float = REFERENCE_RATIO
    passed: bool = True

    def describe(self) -> str:
        if self.method == "exact":
            return "reference: exact solution (damped oscillator)"
        verdict = "PASS" if self.passed else "FAIL"
        return (f"reference: RK4 at dt = {self.dt:.4g} s; RK4 at twice that dt differs from it by {self.change:.3g}, "
                f"{self.change / self.smallest:.3g} x the smallest reported error {self.smallest:.3g} "
                f"(must be < {self.ratio:g}): {verdict}")


@dataclass
class Study:
    scene: str
    params: dict
    duration: float
    times: np.ndarray
    size: float
    runs: list
    reference: ReferenceCheck
    orders: dict

    def summary(self) -> dict:
        return {"scene": self.scene, "params": self.params, "duration": self.duration,
                "save_instants": self.times.tolist(), "size": self.size,
                "reference": asdict(self.reference), "orders": self.orders,
                "cheapest": {f"{t:g}": cheapest(self.runs, t) for t in TARGETS}}


def default_duration(scene) -> float:
    """The study's end time (s): a tenth of the scene's duration.

    Explicit Euler must run at 64x below its largest stable dt on the smallest rung;
    a tenth keeps `massspring study cloth` (and chain) to a few minutes on 2 cores.
    """
    return scene.duration * DEFAULT_DURATION_FRACTION


def save_instants(duration, top_dts, max_saves=MAX_SAVES) -> np.ndarray:
    """Equally spaced instants (s) ending at ``duration``, no closer than the largest dt."""
    count = max(1, int(math.floor(min(max_saves, duration / max(top_dts) + 1e-9))))
    return duration * np.arange(1, count + 1) / count


def dt_ladder(top, interval, rungs=DEFAULT_RUNGS) -> list:
    """``rungs`` dt values halving from at most ``top``, each dividing ``interval`` (s)."""
    first = interval / math.ceil(interval / top - 1e-9)
    return [first / 2 ** k for k in range(rungs)]


def ladder_tops(scene, model, integrators, duration) -> dict:
    """The largest dt (s) of each integrator's ladder, from the stability prediction
    (``massspring.stability.predict``, at the initial state) with a 10% margin: 0.9 x the
    integrator's ``stability_limit`` (explicit: the largest dt at which the stiffest mode
    does not grow, or, if larger, at which its energy doubles in one second; symplectic:
    its predicted limit); for an integrator without one (the implicit ones, RK4), the
    scene's default dt; and at most ``duration`` / 10 (s), so that every run has at least 10 steps.
    """
    from massspring.analysis import stability

    tops = {name: scene.default_dt(name) for name in integrators}
    limited = [name for name in tops if INTEGRATORS[name].stability_limit is not Integrator.stability_limit]
    if limited:
        pred = stability.predict(model)
        for name in limited:
            limit = INTEGRATORS[name].stability_limit(pred)
            if math.isfinite(limit) and limit > 0:
                tops[name] = 0.9 * limit
    return {name: min(top, duration / 10) for name, top in tops.items()}


DEFAULT_INTEGRATORS = STUDIED


def run_study(scene, *, integrators=DEFAULT_INTEGRATORS, duration=None, rungs=DEFAULT_RUNGS,
              ladders=None, cg_tols=DEFAULT_CG_TOLS, newton_tols=DEFAULT_NEWTON_TOLS, preconditioners=("auto",),
              tols=(),
              repeats=DEFAULT_REPEATS,
              time_budget=DEFAULT_TIME_BUDGET, cache=None, use_cache=True,
              reference_ratio=REFERENCE_RATIO, reference_dt=None, progress=None, client=None) -> Study:
    """Run the sweep on ``scene`` (a Scene) and measure every run against the reference.

    ``ladders``: optional {integrator: [dt, ...]} replacing the default ladders (from
    the scene's default dt per integrator, ``dt_ladder``); save instants then follow
    the largest dt given. ``preconditioners``: the runs' of integrators that solve a
    linear system (``solvers.CHOICES``; ``line_preconditioners``), each a line per
    tolerance. ``tols``: error-controlled lines, a run per tolerance and integrator (with
    the first preconditioner). ``reference_dt``: the RK4 step to start the self-check from
    (default: the scene's explicit dt). ``progress``: a callable given each finished Run.
    ``client``: a ``dask.distributed.Client`` to run the runs and the first two RK4
    references on, a task each (None: in this process); further halvings of the
    reference, when its check asks for them, run here. The errors are the same either
    way; wall times on a cluster are those of its workers, sharing their machines.
    """
    integrators = _check_integrators(integrators)
    duration = default_duration(scene) if duration is None else validate.positive_float("duration", duration)
    start_dt = scene.default_dt(SMALLEST_DT) if reference_dt is None else validate.positive_float("reference_dt",
                                                                                                  reference_dt)
    if not duration / start_dt <= MAX_REFERENCE_STEPS:
        raise ValueError(f"duration: {duration:g} s is {duration / start_dt:.3g} steps of the reference's dt "
                         f"({start_dt:.3g} s), more than {MAX_REFERENCE_STEPS:.3g}")
    rungs = validate.count("rungs", rungs)
    repeats = validate.count("repeats", repeats)
    cg_tols = [validate.fraction("cg_tols", t) for t in cg_tols] or list(DEFAULT_CG_TOLS)
    newton_tols = [validate.fraction("newton_tols", t) for t in newton_tols] or list(DEFAULT_NEWTON_TOLS)
    for name in preconditioners:
        validate.choice("preconditioners", name, solvers.CHOICES)
    tols = [Tolerance.of(t).tol for t in tols]
    model = scene.model()
    preconditioners = list(preconditioners) or ["auto"]
    if ladders is None:
        tops = ladder_tops(scene, model, integrators, duration)
        times = save_instants(duration, list(tops.values()))
        ladders = {name: dt_ladder(tops[name], times[0], rungs) for name in integrators}
    else:
        missing = [name for name in integrators if not ladders.get(name)]
        if missing:
            raise ValueError(f"ladders: no dt values for {', '.join(missing)}")
        ladders = {name: [validate.positive_float(f"ladders[{name!r}]", dt) for dt in ladders[name]] for name in integrators}
        times = save_instants(duration, [dt for name in integrators for dt in ladders[name]])
        for name in integrators:
            for dt in ladders[name]:
                reference.steps_between(times, dt, name=f"ladders[{name!r}]")
    size = scene_size(model)

    exact = reference.exact_spring(model, times)
    first = _reference_dt(times, start_dt)
    reference_dts = [] if exact is not None else [first, first / 2]  # RK4's first pair: tasks too
    tasks = [("reference", (model, times, dt, cache, use_cache)) for dt in reference_dts]
    for name in integrators:
        cls, swept = INTEGRATORS[name], hints(name).swept
        solver_tols = [{swept: t} for t in {"cg_tol": cg_tols, "newton_tol": newton_tols}.get(swept, ())]
        for pre in (line_preconditioners(model, name, preconditioners) if cls.traits.linear_solver else [None]):
            for tol in (solver_tols if cls.traits.linear_solver else [{}]):
                for dt in ladders[name]:
                    tasks.append(("run", (model, name, ladders[name][0], dt, tol, pre, times, size, repeats,
                                          time_budget)))
        own = line_preconditioners(model, name, preconditioners)[0] if cls.traits.linear_solver else None
        for t in tols:
            tasks.append(("run", (model, name, ladders[name][0], ladders[name][0], {"tol": t}, own, times, size,
                                  repeats, time_budget)))

    def finished(index, result):
        if progress and index >= len(reference_dts):
            progress(result)

    results = cluster.run_tasks(_task, tasks, client=client, on_result=finished)
    runs = results[len(reference_dts):]
    _repeat(runs, [args for kind, args in tasks if kind == "run"], repeats, time_budget, client)
    known = dict(zip(reference_dts, results[:len(reference_dts)]))
    ref, check = (exact, ReferenceCheck("exact")) if exact is not None else _reference(
        model, times, first, runs, size, cache, use_cache, reference_ratio, known)
    for run in runs:
        _score(run, ref, model, size)
    return Study(scene.name, dict(scene.params), duration, times, size, runs, check, fit_orders(runs))


def line_preconditioners(model, integrator, names) -> list:
    """The preconditioners of ``integrator``'s lines for ``names``: each resolved as that
    integrator's own Simulation resolves it ("auto": block-Jacobi or multigrid by size,
    multigrid with its finest level in f32 only where the integrator gains by it), once."""
    finest_f32 = INTEGRATORS[integrator].finest_f32(model, "f64")
    return list(dict.fromkeys(solvers.resolve(name, model, finest_f32) for name in names))


def _task(kind, args):
    """One task of the study: an RK4 reference trajectory (``reference.rk4``), or a run
    (``kind`` "run": ``_measure``; "time": ``_time``) after ``_warm_up`` (at once when
    this process has compiled the kernels already)."""
    if kind == "reference":
        return reference.rk4(*args)
    model, integrator, warm_dt, dt, tol, preconditioner, times, size, repeats, time_budget = args
    _warm_up(model, integrator, warm_dt, preconditioner)
    if kind == "time":
        return _time(model, integrator, dt, tol, preconditioner, times)
    return _measure(model, integrator, dt, tol, preconditioner, times, size)


def _repeat(runs, args, repeats, time_budget, client):
    """The timed runs after the measured ones, in rounds (each of ``runs``, with its task's
    ``args``, timed once more a round while fewer than ``repeats`` were timed and their
    total is under ``time_budget`` s); each run's ``wall_s`` the least of its times."""
    walls = [[] if run.diverged else [run.wall_s] for run in runs]
    for _ in range(repeats - 1):
        due = [k for k, times in enumerate(walls) if times and sum(times) < time_budget]
        if not due:
            break
        for k, wall in zip(due, cluster.run_tasks(_task, [("time", args[k]) for k in due], client=client)):
            walls[k].append(wall)
    for run, times in zip(runs, walls):
        if times:
            run.wall_s, run.timed_runs = min(times), len(times)


def _warm_up(model, integrator, dt, preconditioner):
    """Compile this integrator's kernels: two steps and then one on a throwaway Simulation,
    so that a per-step kernel is compiled for both orders of its two states and an odd
    count's copy back into the first (``Integrator.settle``) is compiled too."""
    sim = Simulation(model, integrator=integrator, dt=dt, **_solver({}, preconditioner))
    try:
        sim.step(2)
        sim.step(1)
    except DivergenceError:
        pass
    sim.positions  # noqa: B018 - compiles the readback too
    sim.close()  # its fields (if any) go to the pool: the runs below reuse them, compiled


def _solver(tol, preconditioner):
    """Simulation arguments of a run: its tolerance ({"cg_tol": t}, {"newton_tol": t},
    {"tol": t} for an error-controlled run, or {}) and preconditioner (None for
    integrators without a linear solve)."""
    return dict(tol) if preconditioner is None else {**tol, "preconditioner": preconditioner}


def _advance(sim, until, steps):
    """Step ``sim`` to save instant number ``steps`` (a fixed-dt run) or to time ``until``
    (s, an error-controlled one)."""
    if sim.tol is None:
        sim.step(int(steps - sim.steps))
    else:
        sim.advance(until - sim.time)


def _measure(model, integrator, dt, tol, preconditioner, times, size) -> Run:
    """The measured run: states at the save instants, its stepping timed (``wall_s``)."""
    kwargs = _solver(tol, preconditioner)
    run = Run(integrator, dt, tol.get("cg_tol"), preconditioner, tol.get("newton_tol"), tol.get("tol"))
    if run.tol is not None:
        kwargs["horizon"] = float(times[-1])
        counts = np.zeros(len(times))
    else:
        counts = reference.steps_between(times, dt)
    sim = Simulation(model, integrator=integrator, dt=dt, **kwargs)
    positions, wall = [], 0.0
    for until, count in zip(times, counts):
        start = time.perf_counter()
        try:
            _advance(sim, until, count)
        except DivergenceError as exc:
            run.diverged, run.status = True, f"diverged ({exc.cause}, step {exc.step})"
            break
        wall += time.perf_counter() - start
        x = sim.positions
        if not np.all(np.isfinite(x)):
            run.diverged, run.status = True, "diverged (non-finite)"
            break
        positions.append(x)
    run.steps = sim.steps
    run.cg_iterations = int(sum(sim.cg_iterations))
    velocities = sim.velocities
    sim.close()
    if run.diverged:
        return run
    run.positions, run.velocities = np.array(positions), velocities
    if not np.all(np.isfinite(run.velocities)):
        run.diverged, run.status = True, "diverged (non-finite)"
        return run
    run.wall_s, run.timed_runs = wall, 1
    return run


def _time(model, integrator, dt, tol, preconditioner, times) -> float:
    """Seconds of stepping of one more run like ``_measure``'s, to the last save instant
    without stopping at the others, after one untimed step on its fresh Simulation (the
    first launch on its arrays)."""
    kwargs = _solver(tol, preconditioner)
    if "tol" in kwargs:
        kwargs["horizon"] = float(times[-1])
    steps = 0 if "tol" in kwargs else reference.steps_between(times, dt)[-1]
    timed = Simulation(model, integrator=integrator, dt=dt, **kwargs)
    try:
        timed.step(1)
        start = time.perf_counter()
        _advance(timed, times[-1], steps + 1)
        return time.perf_counter() - start
    finally:
        timed.close()


def _rms(diff):
    """RMS over particles (and instants) of the length of (..., 3) differences."""
    return float(np.sqrt(np.mean(np.sum(diff * diff, axis=-1))))


def _score(run, ref, model, size):
    """Fill in a finished run's errors against the reference; mark runaways as diverged."""
    if run.diverged:
        return
    moving = model.free_mask()
    diff = run.positions[:, moving] - ref.positions[:, moving]
    per_instant = np.sqrt(np.mean(np.sum(diff * diff, axis=-1), axis=1)) / size
    if np.any(per_instant > 1):
        k = int(np.argmax(per_instant > 1))
        run.diverged, run.status = True, f"diverged (runaway: error {per_instant[k]:.3g} at t = {ref.times[k]:.4g} s)"
        run.wall_s = None
        return
    run.error = float(per_instant[-1])
    run.error_over_time = _rms(diff) / size
    end = model.energy(run.positions[-1], run.velocities)["total"]
    ref_end = model.energy(ref.positions[-1], ref.velocities[-1])["total"]
    run.energy_error = abs(end - ref_end) / _energy_scale(model, ref)


def _energy_scale(model, ref):
    scale = 0.0
    for x, v in [(model.positions, model.velocities)] + list(zip(ref.positions, ref.velocities)):
        energy = model.energy(x, v)
        scale = max(scale, energy["kinetic"] + energy["spring"])
    return scale if scale > 0 else 1.0


def _smallest_error(runs):
    values = [value for run in runs if not run.diverged
              for value in (run.error, run.error_over_time) if value is not None and value > 0]
    return min(values) if values else math.inf


def _reference_dt(times, dt0):
    """RK4's first step: ``dt0`` made to divide the save interval."""
    return times[0] / math.ceil(times[0] / dt0 - 1e-9)


def _reference(model, times, dt, runs, size, cache, use_cache, ratio, known=None):
    """The RK4 reference trajectory and its check.

    RK4 starts at ``dt`` (``_reference_dt``) and compares it with RK4 at half that dt;
    while the change is not below ``ratio`` x the smallest error of the (provisionally
    scored) runs, it halves again, up to REFERENCE_HALVINGS times. The finer of the
    last pair is the reference. ``known``: {dt: trajectory} already computed.
    """
    known = known or {}

    def rk4(dt):
        return known[dt] if dt in known else reference.rk4(model, times, dt, cache=cache, use_cache=use_cache)

    moving = model.free_mask()
    coarse = rk4(dt)
    for _ in range(REFERENCE_HALVINGS + 1):
        dt /= 2
        fine = rk4(dt)
        diff = coarse.positions[:, moving] - fine.positions[:, moving]
        change = max(_rms(diff[-1]), _rms(diff)) / size if np.all(np.isfinite(diff)) else math.inf
        provisional = [Run(r.integrator, r.dt, r.cg_tol, r.preconditioner, r.newton_tol, positions=r.positions,
                           velocities=r.velocities, diverged=r.diverged) for r in runs]
        for run in provisional:
            _score(run, fine, model, size)
        smallest = _smallest_error(provisional)
        if change < ratio * smallest:
            break
        coarse = fine
    return fine, ReferenceCheck(REFERENCE, dt=dt, change=change, smallest=smallest, ratio=ratio,
                                passed=change < ratio * smallest)


def _check_integrators(integrators):
    names = list(integrators)
    if not names:
        raise ValueError("integrators: at least one is needed")
    for name in names:
        if name not in INTEGRATORS:
            raise ValueError(f"integrators: unknown value {name!r}, expected some of {', '.join(INTEGRATORS)}")
    return names
