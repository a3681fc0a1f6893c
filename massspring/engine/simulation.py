"""``Simulation``: a Model on Taichi fields, stepped by one integrator; ``run`` drives it."""

from __future__ import annotations

import copy
import dataclasses
import math
import textwrap
import weakref
from dataclasses import dataclass, make_dataclass

import numpy as np

from massspring.engine import adaptive, footprint
from massspring.model import ordering
from massspring.passes import PASSES, for_model
from massspring.support import memory, validate
from massspring.model.colliders import COLLIDERS
from massspring.support.defaults import MAX_STEPS, PRECISIONS
from massspring.device import ARCHS, CPU_ARCHS, POOL, ensure_taichi, model_layout
from massspring.support.errors import DivergenceError, SimulationClosedError
from massspring.integrators import DEFAULT, INTEGRATORS, OPTIONS, takers, untaken
from massspring.kernels import divergence
from massspring.kernels import state as state_kernels
from massspring.model.terms import active_terms
from massspring.model import Model, feedback
from massspring.engine.schedule import Schedule
from massspring.solvers import PRECONDITIONERS, resolve
from massspring.support.validate import real_array

LOOPS = ("auto", "serial", "parallel")
# Springs below which serial kernels beat parallel ones on this project's 2-core CPU
# machines, where a parallel loop's launch costs more than two threads save on small
# models. On the Intel one, symplectic steps and block-Jacobi CG iterations were faster
# serial up to 880,898 springs and parallel at 1,567,746 (benchmarks/switch_point.py;
# benchmarks/results/switch_point_intel.json); on the AMD one (an older revision,
# results/switch_point.json) symplectic steps were faster serial at 390,658 springs
# and CG iterations faster parallel. Simulation(loops=...) overrides it.
SERIAL_BELOW = 1_000_000
STEPS_PER_LAUNCH = 2**30  # explicit steps per kernel call at most (the count is an int32 there)
DIVERGENCE_FACTOR = 100.0  # see divergence_check
F32_MAX_MAGNITUDE = 1e18  # model values an f32 run accepts: their squares stay within f32's 3.4e38


# A simulation's settings (see ``Simulation``), fixed at construction: the run's own,
# then every integrator's solver options (``integrators.OPTIONS``).
Settings = make_dataclass("Settings", [(name, object) for name in
                                       ("integrator", "dt", "precision", "arch", "loops", *OPTIONS,
                                        "tol", "min_dt", "max_dt", "horizon")], frozen=True)
Settings.__module__ = __name__  # where pickle finds it


def _check_carried(carried, names, n):
    """``carried`` (None or a dict) checked against an integrator's ``carried_names``."""
    if carried is None:
        return None
    if not isinstance(carried, dict) or set(carried) != set(names):
        got = sorted(carried) if isinstance(carried, dict) else type(carried).__name__
        raise ValueError(f"carried: expected the keys {sorted(names)} (Simulation.carried_state() of this "
                         f"integrator and model), got {got}")
    out = {}
    for name, (dtype, shape) in names.items():
        arr = np.asarray(carried[name])
        if arr.shape != (n, *shape) or arr.dtype.kind not in ("iu" if np.dtype(dtype).kind == "i" else "fiu"):
            raise ValueError(f"carried[{name!r}]: expected shape {(n, *shape)} of {np.dtype(dtype).name}, "
                             f"got shape {arr.shape} of {arr.dtype}")
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"carried[{name!r}]: contains non-finite values")
        out[name] = np.ascontiguousarray(arr.astype(dtype))
    return out


@dataclass(frozen=True)
class Snapshot:
    """A ``Simulation.snapshot()``: positions, velocities (n, 3) in the model's
    numbering, steps taken, ``carried_state()``, each pass's ``snapshot()`` and the run's
    counters (CG and Newton iteration lists' lengths, line-search cuts, failures)."""

    positions: np.ndarray
    velocities: np.ndarray
    steps: int
    carried: dict
    passes: tuple
    counters: tuple
    time: float | None = None  # an error-controlled run's time (s)
    chosen: frozenset | None = None  # the intervals a feedback controller has chosen (``Schedule.snapshot``)


def divergence_check(model: Model, factor=DIVERGENCE_FACTOR, driven=0.0):
    """The (base, gx0, factor) of the per-step divergence check (kernels/divergence.py).

    A state is rejected if a position or velocity is not finite, or if its kinetic
    energy exceeds ``factor * (base + W)`` with W >= 0 the work the uniform forces
    (gravity and any other ``uniform`` term) have done since the start (sum m a . (x -
    x0), a = ``Model.external_acceleration``; gx0 is ``Model.external_work`` of x0).
    ``base`` (J) is the initial kinetic plus spring energy plus a floor, the kinetic
    energy of the whole mass moving at one scene size per second (size: the diagonal of
    the initial bounding box, or the longest rest length if larger; 1 m if both are 0)
    plus the fastest drive: the wind speed, the fastest pin or twice the fastest
    collider (what the air, a moving pin or a collider can give the particles; the
    controls' pins, wind and rest lengths of every interval included: ``Controls.speeds``;
    ``driven`` m/s, what a feedback controller can drive: ``Controller.top_speed``).
    Physically kinetic energy never exceeds base - floor + W (springs only store and
    dampers only dissipate), so ``factor`` = 100 leaves room for the energy error of a
    stable integrator (symplectic Euler's oscillates by up to ~40x just below its limit)
    while an unstable mode, growing geometrically, crosses it within a few dozen steps.
    """
    energy = model.energy(model.positions, model.velocities)
    extent = float(np.linalg.norm(np.ptp(model.positions, axis=0)))
    size = max(extent, float(model.rest_lengths.max(initial=0.0))) or 1.0
    drive = max([float(np.linalg.norm(model.wind))] + [float(np.linalg.norm(v)) for v in model.pin_velocity]
                + [2 * float(np.linalg.norm(c.velocity)) for c in model.colliders]
                + ([model.controls.speeds(model.positions[model.fixed], model.rest_lengths)]
                   if model.controls is not None else []) + [float(driven)])
    floor = 0.5 * float(model.masses.sum()) * (size + drive) ** 2
    return (energy["kinetic"] + energy["spring"] + floor, model.external_work(model.positions), float(factor))


def pin_work(model: Model, driven=0.0) -> float:
    """c (J/s^2) such that c t^2 bounds the energy moving pins can have put into the model
    by time t (s), which ``base`` of ``divergence_check`` grows by as the run goes: pins
    at most s m/s fast (their velocities, the controls' of every interval) are at most 2 s t
    further apart than at the start, which stores at most (sum of the stiffnesses) (2 s t)^2
    / 2 in the springs, and does about as much work. 0 without moving pins. Before, pins
    pulling a chain apart at 1 m/s ended its run as "diverged" (issue 60). ``driven``: what
    a feedback controller can drive (m/s, ``Controller.top_speed``), counted as a pin's speed."""
    if not model.has_fixed or not model.n_springs:
        return 0.0
    speeds = [float(np.linalg.norm(v)) for v in model.pin_velocity]
    if model.controls is not None and model.controls.pin_targets is not None:
        speeds.append(float(np.linalg.norm(model.controls.pin_velocities(model.positions[model.fixed]), axis=-1).max()))
    speed = max(speeds + [float(driven)], default=0.0)
    return 2.0 * float(model.stiffness.sum()) * speed * speed


def default_cg_max_iter(model: Model) -> int:
    """3 x (free particles): the exact-arithmetic bound of CG on the free DOFs, at least 100."""
    free = model.n_particles - model.fixed.size
    return min(max(100, 3 * free), validate.MAX_INT32)


class Simulation:
    """Steps a :class:`Model` with one integrator on Taichi kernels.

    Parameters
    ----------
    model : Model
    integrator : {integrators}
        (``integrators.INTEGRATORS``)
    dt : float, s, > 0
        The step; with ``tol``, the first step.
    tol : float, optional, 1e-14 .. (the error the study reports: RMS position error of
        the moving particles over the scene's size)
        An error-controlled run: each step's size is chosen from an estimate of its
        local error so that the error at the end of ``horizon`` s is about ``tol``
        (``engine.adaptive``); Newton's and CG's tolerances follow from it (giving
        ``newton_tol`` or ``cg_tol`` too is a ValueError). None (default): fixed steps of dt.
    min_dt, max_dt : float, s, optional (with ``tol``)
        Bounds on the steps: default 1e-9 x horizon and the horizon. A step that would
        fall below min_dt raises ``StepSizeError`` (a ``DivergenceError``).
    horizon : float, s, optional (with ``tol``)
        The run's duration the tolerance is for (default 1 s).
    precision : "f64" (default) | "f32"
{options}    arch : Taichi arch name, "cpu" by default; one that cannot start is a ValueError.
    loops : "auto" (default) | "serial" | "parallel"
        Serial kernels (a whole CG solve, or many explicit steps, per launch) or
        parallel kernels (one launch per phase); "auto" picks parallel from
        ``SERIAL_BELOW`` springs on the CPU (from the preconditioner's own
        ``serial_below`` where it has one: multigrid's is lower), and always on other
        archs. Either gives
        the same bits for any thread count (fixed-block reductions). Between them,
        explicit, symplectic and RK4 steps agree to the bit and implicit solves to
        round-off (the two kernels' compilers may contract multiplies and adds
        differently).

    controller : ``massspring.Controller``, optional
        A feedback controller (``model.feedback``): as the run enters each interval of
        the model's ``controls``, it chooses that interval's values of the controls it
        drives from the state then (``control_states``). ``set_state`` has it choose
        again from the new state's interval on.

    Only what the run needs is allocated and compiled: no CG vectors for the
    explicit integrators, no damping term with kd = 0, no gravity term with g = 0,
    no pin filter without pinned particles, no pin-velocity read without moving pins,
    no collider code or array without colliders, no drag term without drag (see
    ``info()``). Settings are read-only.
    ``close()`` hands the fields back for reuse; any later call raises
    ``SimulationClosedError``.
    """

    def __init__(self, model, integrator=DEFAULT, dt=1e-2, precision="f64", arch="cpu", loops="auto",
                 tol=None, min_dt=None, max_dt=None, horizon=None, controller=None, **options):
        if not isinstance(model, Model):
            raise ValueError(f"model: expected a massspring.Model, got {type(model).__name__}")
        if controller is not None:
            feedback.check(controller, model.controls)
        unknown = sorted(set(options) - set(OPTIONS))
        if unknown:
            raise TypeError(f"Simulation: unexpected keyword argument {unknown[0]!r} (solver options: "
                            f"{', '.join(OPTIONS)})")
        validate.choice("integrator", integrator, tuple(INTEGRATORS))
        for lacks, names in untaken(integrator, [name for name, value in options.items() if value is not None]).items():
            raise ValueError(f"{names[0]}: {integrator!r} {lacks}; {'these options are' if len(names) > 1 else 'it is'} "
                             f"for {', '.join(takers(names[0]))}")
        validate.choice("precision", precision, PRECISIONS)
        dt = validate.positive_float("dt", dt)
        tolerance = None
        self._min_dt_given = min_dt is not None  # else StepSizeError says where min_dt comes from
        if tol is None:
            for name, value in (("min_dt", min_dt), ("max_dt", max_dt), ("horizon", horizon)):
                if value is not None:
                    raise ValueError(f"{name}: only for an error-controlled run (give tol)")
        else:
            tolerance = adaptive.Tolerance.of(tol, min_dt, max_dt, horizon)
            for name in ("newton_tol", "cg_tol"):
                if options.get(name) is not None:
                    raise ValueError(f"{name}: an error-controlled run (tol) derives it from tol; give one or "
                                     f"the other")
            if max_dt is None:
                tolerance = adaptive.stable_bound(tolerance, INTEGRATORS[integrator], model)
        if model.controls is not None:
            if tolerance is None:
                model.controls.steps_per_interval(dt)
            if model.controls.pin_targets is not None and not INTEGRATORS[integrator].traits.keyframed_pins:
                raise ValueError(f"integrator: {integrator!r} does not move keyframed pins "
                                 f"(controls.pin_targets); these do: "
                                 f"{', '.join(k for k, c in INTEGRATORS.items() if c.traits.keyframed_pins)}")
        options = {name: option.default if options.get(name) is None else option.check(options[name])
                   for name, option in OPTIONS.items()}
        if options["cg_max_iter"] is None:
            options["cg_max_iter"] = default_cg_max_iter(model)
        preconditioner = options["preconditioner"]
        validate.choice("loops", loops, LOOPS)
        validate.choice("arch", arch, ARCHS)
        if precision == "f32":
            _check_f32_range(model)
        ensure_taichi(arch)
        preconditioner = resolve(preconditioner, model, INTEGRATORS[integrator].finest_f32(model, precision))
        if loops == "auto":
            below = SERIAL_BELOW
            if INTEGRATORS[integrator].traits.linear_solver:
                below = PRECONDITIONERS[preconditioner].serial_below or SERIAL_BELOW
            loops = "serial" if model.n_springs < below and arch in CPU_ARCHS else "parallel"
        self._model = model
        options["preconditioner"] = preconditioner
        self._settings = Settings(integrator, dt, precision, arch, loops, **options,
                                  **({"tol": None, "min_dt": None, "max_dt": None, "horizon": None}
                                     if tolerance is None else vars(tolerance)))
        self._check = divergence_check(model, driven=feedback.top_speed(controller))
        self._pin_work = pin_work(model, feedback.top_speed(controller))
        self._steps = 0
        self._cg_iterations = []
        self._newton_iterations = []
        self._cuts = 0
        self._sizes = []  # the sizes (s) of the latest steps of a run whose clock runs (step_sizes)
        self._sizes_from = 0  # the step they start from
        self._cg_failures = 0

        cls = INTEGRATORS[integrator]
        memory.check(footprint.run_bytes(footprint.Sketch.of(model), integrator, precision, preconditioner,
                                         model_built=not ordering.wanted(model)),  # else a renumbered copy
                     f"model: {model.n_particles:,} particles and {model.n_springs:,} springs; "
                     f"a run of it ({integrator})")
        self._order = ordering.plan(model)
        # the pins' rows inside: the model's rows in this order (``ordering.renumbered``'s)
        self._pin_order = None if self._order is None else np.argsort(self._order.inverse[model.fixed], kind="stable")
        inner = model if self._order is None else self._order.model
        layout = model_layout(inner, precision)
        cls.declare(layout, inner, self._settings)
        kinds = for_model(inner)
        for kind in kinds:
            kind.declare(layout, inner)
        self._layout_names = [name for name in layout.decls if name not in ("size", "check", "partial")]
        self._bytes = layout.nbytes()
        dev = layout.allocate()
        dev.check[None] = self._check
        self._integrator = cls(dev, inner, self._settings)
        self._inner = inner
        self._feedback = controller
        self._control_states = {}  # interval -> the ControlState its controls were chosen from
        self._schedule = None if model.controls is None else self._new_schedule(dev, None if tolerance else dt)
        self._passes = tuple(kind(dev, self._integrator.cfg, inner, self._integrator.serial, dt) for kind in kinds)
        self._release = weakref.finalize(self, _release, dev, self._integrator, self._passes)
        self._controller = self._estimator = self._read_plan = None
        self._calm, self._batch_size = 0, adaptive.BATCH_FIRST  # calm steps in a row; the next batch's steps
        if tolerance is not None:
            self._integrator.clock = 0.0
            size = adaptive.scene_size(model)
            self._controller = adaptive.Controller(tolerance, dt, size)
            cls = self._integrator.traits
            self._estimator = adaptive.Estimator(cls.order, cls.error_constant, np.flatnonzero(inner.free_mask()),
                                                 size, tolerance.horizon, model.colliders)
            for p in self._passes:
                p.watch_moves()

    # ------------------------------------------------------------------ settings

    @property
    def model(self) -> Model:
        return self._model

    @property
    def settings(self) -> Settings:
        return self._settings

    integrator = property(lambda self: self._settings.integrator, doc="Integrator name.")
    dt = property(lambda self: self._settings.dt, doc="Time step (s).")
    precision = property(lambda self: self._settings.precision, doc='"f64" or "f32".')
    arch = property(lambda self: self._settings.arch, doc="Taichi arch.")
    loops = property(lambda self: self._settings.loops, doc='"serial" or "parallel" (resolved from "auto").')
    # and a read-only property per solver option (integrators.OPTIONS), set below the class

    @property
    def check(self) -> tuple:
        """(base, gx0, factor) of the divergence check (``divergence_check``)."""
        return self._check

    # ------------------------------------------------------------------ state

    @property
    def closed(self) -> bool:
        return not self._release.alive

    def _open(self):
        if not self._release.alive:
            raise SimulationClosedError("Simulation: closed (close() was called); create a new Simulation")
        return self._integrator

    @property
    def steps(self) -> int:
        """Steps taken."""
        return self._steps

    @property
    def time(self) -> float:
        """Simulated time (s): steps x dt (an error-controlled or replayed run's clock)."""
        if self._clocked:
            return self._open().clock
        return self._steps * self._settings.dt

    @property
    def _clocked(self) -> bool:
        """Whether steps vary in size (an error-controlled run, or one that replays one)."""
        return self._open().clock is not None

    @property
    def step_sizes(self) -> np.ndarray:
        """(k,) s: the sizes of the last k steps of an error-controlled or replayed run, in
        order (all of them since it started; ``set_state`` and ``restore`` cut them back
        to the state set, or start them afresh at a state not among them). Empty for a run
        of fixed steps of dt. What ``replay`` and ``massspring.gradient(dts=...)`` take."""
        return np.array(self._sizes, dtype=np.float64)

    tol = property(lambda self: self._settings.tol, doc="The error-controlled run's tolerance (None: fixed dt).")

    def control_stats(self):
        """An error-controlled run's steps: accepted (and "batched": of them, those an
        explicit run held at max_dt took in calm batches, ``engine.adaptive``), rejected by
        cause ("error": the estimate above its bound, "solver": Newton or CG missed,
        "divergence": the check refused the state), the smallest and largest accepted step
        and the next (s); None with a fixed dt."""
        return None if self._controller is None else self._controller.stats()

    @property
    def positions(self) -> np.ndarray:
        """(n, 3) float64 copy of the current positions (m)."""
        integrator = self._open()
        return self.to_user(integrator.state.x.to_numpy()[: self._model.n_particles].astype(np.float64))

    @property
    def velocities(self) -> np.ndarray:
        """(n, 3) float64 copy of the current velocities (m/s)."""
        integrator = self._open()
        return self.to_user(integrator.state.v.to_numpy()[: self._model.n_particles].astype(np.float64))

    def to_user(self, rows):
        """Rows (n, ...) in the run's inner numbering (``numbering``) as the model numbers its particles."""
        return rows if self._order is None else self._order.to_user(rows)

    def to_inner(self, rows):
        """Rows (n, ...) in the model's numbering as the run numbers its particles inside."""
        return rows if self._order is None else self._order.to_inner(rows)

    @property
    def numbering(self):
        """The run's renumbering of the model's particles and springs for locality
        (``model.ordering.Order``), or None where it keeps the model's."""
        return self._order

    # ------------------------------------------------------------------ seams (gradients, step control)

    @property
    def stepper(self):
        """The integrator instance that steps this run (``integrators.base.Integrator``:
        its ``keep``, ``history``, ``adjoint`` and ``adjoint_steps`` serve a gradient's run)."""
        return self._open()

    @property
    def passes(self) -> tuple:
        """The passes this run holds (instances of ``passes.PASSES``' classes), in the order they run."""
        return self._passes

    @property
    def schedule(self):
        """The control schedule (``engine.schedule.Schedule``), or None without controls."""
        return self._schedule

    @property
    def controller(self):
        """The feedback controller (``model.feedback.Controller``), or None."""
        return self._feedback

    @property
    def control_states(self) -> dict:
        """interval -> the ``ControlState`` the controller chose its controls from (a copy)."""
        return dict(self._control_states)

    def _new_schedule(self, dev, dt):
        return Schedule(self._inner, dev, dt, None if self._feedback is None else self._choose,
                        self._integrator.serial)

    def _choose(self, s):
        """Interval s's values from the feedback controller, at the current state."""
        n = self._model.n_particles
        rows = np.empty((n, 6))
        integrator = self._open()
        state_kernels.read_state(integrator.state, rows, n, (), integrator.serial)  # as it is, unsettled: one launch
        state = feedback.ControlState(self.to_user(rows[:, :3]), self.to_user(rows[:, 3:]), self.time, s)
        self._control_states[s] = state
        out = feedback.outputs(self._feedback, state, self._model.controls)
        if "pin_targets" in out and self._pin_order is not None:
            out["pin_targets"] = out["pin_targets"][self._pin_order]
        return out

    def snapshot(self) -> "Snapshot":
        """Everything a step changes, kept to come back to (``restore``): the state, what
        the integrator carries, each pass's state and counters, and the run's counters.
        For a step that is to be rejected and retried."""
        self._open()
        return Snapshot(self.positions, self.velocities, self._steps, self.carried_state(),
                        tuple(p.snapshot() for p in self._passes),
                        (len(self._cg_iterations), len(self._newton_iterations), self._cuts, self._cg_failures),
                        self.time if self._clocked else None, self._chosen())

    def _chosen(self):
        return None if self._schedule is None else self._schedule.snapshot()

    def restore(self, snapshot: "Snapshot"):
        """Back to ``snapshot`` (a ``snapshot()`` of this run): a run continued from here
        equals, to the bit, one continued from where the snapshot was taken."""
        if not isinstance(snapshot, Snapshot) or len(snapshot.passes) != len(self._passes):
            raise ValueError("snapshot: expected a Simulation.snapshot() of this run")
        history = None if self._estimator is None else self._estimator.points
        self.set_state(snapshot.positions, snapshot.velocities, snapshot.steps, snapshot.carried, snapshot.time)
        if history is not None:
            self._estimator.points = history  # the estimate's history of the run, not a restart's
        for p, kept in zip(self._passes, snapshot.passes):
            p.restore(self._integrator.state, kept)
        if snapshot.chosen is not None:
            self._schedule.restore(snapshot.chosen)
        cg, newton, self._cuts, self._cg_failures = snapshot.counters
        del self._cg_iterations[cg:], self._newton_iterations[newton:]
        return self

    @property
    def solver_stats(self):
        """The last implicit step's ``solvers.SolverStats`` (None before the first step or if explicit)."""
        return self._open().stats

    @property
    def cg_iterations(self) -> list:
        """CG iterations of every implicit step so far (all its Newton iterations' together; a copy)."""
        return list(self._cg_iterations)

    @property
    def cg_failures(self) -> int:
        """Implicit steps that missed their tolerance (CG's; Newton's for a Newton-solved integrator)."""
        return self._cg_failures

    @property
    def newton_iterations(self) -> list:
        """Newton iterations (linear solves) of every step so far (Newton-solved integrators; a copy)."""
        return list(self._newton_iterations)

    def pass_stats(self) -> dict:
        """name -> ``stats()`` of each pass the run holds (``passes.PASSES``; each pass's own
        property, e.g. ``self_collision_stats``, gives one)."""
        return {p.name: p.stats() for p in self._passes}

    @property
    def line_search_cuts(self) -> int:
        """Line-search halvings of all steps so far (Newton-solved integrators)."""
        return self._cuts

    def carried_state(self) -> dict:
        """What the integrator carries from one step to the next besides positions and
        velocities, as numpy arrays with a row per particle: for the implicit integrator
        with colliders, its contact memory ("released": contacts that pulled, "stick":
        sticking particles, "fric": kinetic friction impulses, N s), for the Newton-solved
        integrators the previous state, and with self-collision the pass's anchors and free
        distances ("sc_anchor", "sc_free", m); else empty. Give it back to ``set_state``
        for a restart that continues to the bit."""
        carried = self._open().carried()
        for p in self._passes:
            carried.update(p.carried_state())
        return {name: self.to_user(rows) for name, rows in carried.items()}

    def control_state(self) -> dict:
        """An error-controlled run's step-size controller and the accepted states its error
        estimate draws on, as numpy arrays (``adaptive.CONTROL_KEYS``; empty for a run of fixed
        steps): "controller" (``adaptive.CONTROLLER_FIELDS``), "batching" (calm steps in a
        row, the next batch's size) and the estimator's "est_*" (``Estimator.state``,
        inner numbering). With ``carried_state()`` and ``time``, what ``set_state`` needs
        to continue the run to the bit."""
        if self._controller is None:
            return {}
        return {"controller": self._controller.state(),
                "batching": np.array([self._calm, self._batch_size], dtype=np.float64), **self._estimator.state()}

    def _carried_names(self, integrator) -> dict:
        names = dict(integrator.carried_names())
        for p in self._passes:
            names.update(p.carried)
        return names

    def set_state(self, positions, velocities, steps=0, carried=None, time=None, control=None):
        """Continue from a given state (a restart): ``positions`` (n, 3) in m,
        ``velocities`` (n, 3) in m/s, ``steps`` taken so far (``time`` is steps x dt:
        where moving pins and colliders are; an error-controlled run's ``time``, s, is
        given, by default steps x dt), ``carried``: a ``carried_state()`` of the
        same model and integrator (None: such memory starts afresh, e.g. no contact
        sticks yet), ``control``: an error-controlled run's ``control_state()`` (None:
        its error estimate starts afresh from here, its next step is the one it was
        given as ``dt``).

        The Model stays as it is (rest lengths, pins, the divergence check), so a run
        of k steps, saved and set here (with its ``carried_state()``; an
        error-controlled run with its ``time`` and ``control_state()`` too), then
        continued for j steps equals an unbroken run of k + j steps to the bit (in f64,
        with the same integrator and dt or tol). Values must be finite (and within an f32 run's range);
        a pinned particle's velocity must be its pin velocity (``Model.pin_velocity``,
        0 by default; with keyframed pins the velocity it last moved with). Raises
        ValueError naming the argument.
        """
        integrator = self._open()
        n = self._model.n_particles
        arrays = {}
        for name, value in (("positions", positions), ("velocities", velocities)):
            arr = real_array(name, value)
            if arr.shape != (n, 3):
                raise ValueError(f"{name}: expected shape ({n}, 3) (one row per particle), got shape {arr.shape}")
            if self.precision == "f32" and arr.size and np.abs(arr).max() > F32_MAX_MAGNITUDE:
                raise ValueError(f"{name}: {np.abs(arr).max():g} is beyond what an f32 run holds "
                                 f"(|value| <= {F32_MAX_MAGNITUDE:g})")
            arrays[name] = np.ascontiguousarray(arr)
        steps = validate.count("steps", steps, low=0, high=MAX_STEPS)
        if time is not None and not self._clocked:
            raise ValueError("time: only for an error-controlled or replayed run (tol, replay); a fixed-dt run's "
                             "time is steps x dt")
        clock = None
        if self._clocked:
            clock = steps * self.dt if time is None else validate.real_number("time", time, 0.0, ">=")
        fixed, pinned = self._model.fixed, self._pin_velocity_before(steps, clock)
        wrong = np.flatnonzero(np.any(arrays["velocities"][fixed] != pinned, axis=1))
        if wrong.size:
            k = int(wrong[0])
            raise ValueError(f"velocities: particle {int(fixed[k])} is pinned, so its velocity must be its pin "
                             f"velocity {pinned[k].tolist()}, got {arrays['velocities'][fixed[k]].tolist()}")
        carried = _check_carried(carried, self._carried_names(integrator), n)
        if control is not None and self._controller is None:
            raise ValueError("control: only for an error-controlled run (tol)")
        if control is not None:
            if not isinstance(control, dict) or set(control) != set(adaptive.CONTROL_KEYS):
                got = sorted(control) if isinstance(control, dict) else type(control).__name__
                raise ValueError(f"control: expected the keys {sorted(adaptive.CONTROL_KEYS)} "
                                 f"(Simulation.control_state() of an error-controlled run of this model), got {got}")
            controller = adaptive.Controller(self._controller.tolerance, self.dt, self._controller.size)
            estimator = copy.copy(self._estimator)
            controller.load(control["controller"])
            estimator.load(control)  # both checked before either is taken
            batching = np.asarray(control["batching"], dtype=np.float64)
            if batching.shape != (2,) or not (0 <= batching[0] <= adaptive.CALM_TRIES
                                              and adaptive.BATCH_FIRST <= batching[1] <= adaptive.BATCH_MOST):
                raise ValueError(f"control['batching']: expected (calm steps, batch size) within (0..."
                                 f"{adaptive.CALM_TRIES}, {adaptive.BATCH_FIRST}...{adaptive.BATCH_MOST})")
        arrays = {name: self.to_inner(rows) for name, rows in arrays.items()}
        if carried is not None:
            carried = {name: self.to_inner(rows) for name, rows in carried.items()}
        theirs = {name for p in self._passes for name in p.carried}
        own = None if carried is None else {k: v for k, v in carried.items() if k not in theirs}
        integrator.load_state(arrays["positions"], arrays["velocities"], own)
        for p in self._passes:
            p.load(integrator.state, None if carried is None else {k: carried[k] for k in p.carried})
        integrator.steps = steps  # moving pins and colliders are where they are at steps x dt
        first = self._sizes_from
        if first <= steps <= first + len(self._sizes):
            del self._sizes[steps - first:]
        else:
            self._sizes.clear()
            self._sizes_from = steps
        self._steps = steps
        if clock is not None:
            integrator.clock = clock
            if self._estimator is not None:
                self._estimator.points = []  # the history starts afresh at the next step
        if control is not None:
            self._controller, self._estimator = controller, estimator
            self._calm, self._batch_size = int(batching[0]), int(batching[1])
            self._current = self._read_state(integrator)  # what a rejected first try goes back to
        if self._schedule is not None:
            self._schedule.forget(self.time)  # a feedback controller chooses again from here
        return self

    def _pin_velocity_before(self, steps, clock=None):
        """(k, 3) m/s: the pins' velocities in a state after ``steps`` steps (at time
        ``clock``, s, in an error-controlled run): their pin velocity, or with keyframed
        pins (``Controls.pin_targets``) the velocity each last moved with."""
        model, schedule = self._model, self._schedule
        if steps == 0 or schedule is None or schedule.pins is None:
            return model.pin_velocity
        s = schedule.interval(steps - 1) if clock is None else schedule.before(clock)
        if s >= schedule.count:
            return np.zeros_like(model.pin_velocity)
        velocities = schedule.pins[s]  # the run's rows (a feedback controller's choice, where it drives the pins)
        if self._pin_order is None:
            return velocities
        out = np.empty_like(velocities)
        out[self._pin_order] = velocities
        return out

    # ------------------------------------------------------------------ stepping

    def step(self, n=1):
        """Advance ``n`` steps of size ``dt`` (an error-controlled run: ``n`` accepted steps
        of the sizes it chooses).

        Every step is checked (``divergence_check``). A step whose state has a
        non-finite value or runaway kinetic energy raises ``DivergenceError``
        naming it; the simulation then holds the last good state (``steps``,
        ``time``, ``positions`` and ``velocities`` are those of the step before).
        An error-controlled run retries such a step, and one whose error is too large
        or whose solve failed, with a smaller one; it raises ``StepSizeError`` (a
        ``DivergenceError``) where that would be below ``min_dt``.
        """
        integrator = self._open()
        n = validate.count("n", n, low=0, high=MAX_STEPS)
        try:
            if self._controller is not None:
                taken = 0
                while taken < n:
                    taken += self._controlled_step(integrator, math.inf, most=n - taken)
            else:
                self._advance(integrator, n)
        finally:
            integrator.settle()
        return self

    def replay(self, sizes):
        """Advance by steps of the given ``sizes`` (s, each > 0 and finite): the
        ``step_sizes`` of an error-controlled run, taken again as it took them (controls,
        moving pins and colliders by time; BDF2 with its variable-step coefficients), with
        this run's own solver tolerances and no error control (``massspring.gradient``
        differentiates such a run). Only for a run without ``tol``: from its start (step
        0) its clock runs from then on, its ``time`` the sum of the sizes. Divergence
        raises ``DivergenceError`` as ``step`` does. Empty ``sizes`` only starts the clock."""
        integrator = self._open()
        sizes = real_array("sizes", sizes)
        if sizes.ndim != 1 or not np.all(np.isfinite(sizes)) or np.any(sizes <= 0):
            raise ValueError(f"sizes: expected a 1-D array of step sizes (s), each finite and > 0, got "
                             f"{'shape ' + str(sizes.shape) if sizes.ndim != 1 else 'a size <= 0 or not finite'}")
        if self._controller is not None:
            raise ValueError("sizes: an error-controlled run (tol) chooses its own steps; replay its step_sizes on a "
                             "Simulation without tol")
        if integrator.clock is None:
            if self._steps:
                raise ValueError(f"sizes: a run of fixed steps replays from its start only (it has taken "
                                 f"{self._steps:,} steps)")
            integrator.clock = 0.0
            if self._schedule is not None:  # the controls by time: an interval need not be whole steps
                self._schedule = self._new_schedule(integrator.dev, None)
        try:
            for h in sizes.tolist():
                integrator.dt = h
                for p in self._passes:
                    p.dt = h
                done, check = self._one_step(integrator, integrator.clock)
                self._raise_if_diverged(check)
                self._sizes.append(h)
        finally:
            integrator.settle()
        return self

    def advance(self, seconds):
        """Advance by ``seconds`` (s) of simulated time, ending on it exactly: an
        error-controlled run shortens its last step to land there; a fixed-dt run takes
        seconds / dt steps, which must be a whole number (ValueError naming ``seconds``)."""
        integrator = self._open()
        seconds = validate.real_number("seconds", seconds, 0.0, ">=")
        if self._controller is None:
            ratio = seconds / self.dt
            steps = round(ratio)
            if abs(ratio - steps) > 1e-9 * max(1.0, ratio):
                raise ValueError(f"seconds: {seconds:g} s is not a whole number of steps of dt {self.dt:g} s "
                                 f"(a fixed-dt run; give tol for an error-controlled one)")
            return self.step(steps)
        return self._advance_to(integrator.clock + seconds)

    def _advance_to(self, end, until=None):
        """Error-controlled steps toward time ``end`` (s), the last landing on it, until the
        clock reaches ``until`` (s, at most ``end``; default ``end``): ``run_for``'s
        progress points, which no step lands on."""
        integrator = self._open()
        until = end if until is None else until
        try:
            while integrator.clock < until and integrator.clock < end:
                self._controlled_step(integrator, end, stop=until)
        finally:
            integrator.settle()
        return self

    def _read_state(self, integrator):
        """(x, v) (n, 3) float64 of the current state, in the run's inner numbering, and
        the arrays of the integrator's ``carried_fields`` (name -> (n,) or (n, k)), read
        in one launch (its columns laid out once a run: ``_read_plan``)."""
        integrator.settle()
        if self._read_plan is None:
            names, extra, rows, column = integrator.carried_names(), [], {}, 6
            for name, field in integrator.carried_fields().items():
                width = names[name][1][0] if names[name][1] else 0
                extra.append((getattr(integrator.dev, field), column, width))
                rows[name] = slice(column, column + width) if width else column
                column += max(width, 1)
            self._read_plan = (tuple(extra), rows, column)
        extra, rows, columns = self._read_plan
        out = np.empty((self._model.n_particles, columns))
        state_kernels.read_state(integrator.state, out, self._model.n_particles, extra, integrator.serial)
        return out[:, :3], out[:, 3:6], {name: out[:, where] for name, where in rows.items()}

    def _kept(self):
        """What a rejected try goes back to besides the state and the integrator's carried
        fields (``_controlled_step`` holds those): a ``Snapshot`` without them, its
        ``carried`` only the integrator's ``carried_values``."""
        return Snapshot(None, None, self._steps, self._integrator.carried_values(), tuple(p.snapshot() for p in self._passes),
                        (len(self._cg_iterations), len(self._newton_iterations), self._cuts, self._cg_failures),
                        self._integrator.clock, self._chosen())

    def _carried_of(self, integrator, rows, kept):
        """``carried_state()`` of the state a try started from: the integrator's arrays
        from ``rows``, read with that state (``_read_state``), and the passes' from their
        snapshots in ``kept`` (``_kept``); None if nothing is carried."""
        if not self._carried_names(integrator):
            return None
        carried = {**integrator.carried(rows), **kept.carried}
        for _, theirs in kept.passes:
            carried.update(theirs)
        return {name: self.to_user(values) for name, values in carried.items()}

    def _controlled_step(self, integrator, end, most=math.inf, stop=None) -> int:
        """One accepted step of an error-controlled run (``engine.adaptive``), ending at
        ``end`` (s) if the step would pass it or the end of the control interval it is in,
        after as many rejected tries as it takes; or, in a calm stretch of an explicit run,
        a batch of at most ``most`` steps ending by ``stop`` (s, default ``end``: ``_batch``).
        Returns the steps accepted."""
        ctl, est, schedule = self._controller, self._estimator, self._schedule
        t = integrator.clock
        if not est.points:
            self._current = self._read_state(integrator)
            est.reset(t, *self._current[:2])
        if schedule is not None:
            end = min(end, schedule.end(t))
        if self._calm >= adaptive.CALM_TRIES and most > 1:
            taken = self._batch(integrator, end, end if stop is None else min(stop, end), most)
            if taken:
                return taken
        while True:
            h = ctl.dt
            landing = t + adaptive.STRETCH * h >= end
            if landing:
                h = end - t
            elif t + 2 * h > end:  # two even steps to the end rather than a sliver last
                h = 0.5 * (end - t)
            kept = self._kept()
            integrator.dt = h
            for p in self._passes:
                p.dt = h
            change = est.velocity_change()
            for name in ("newton_tol", "cg_tol"):
                if getattr(integrator, name) is not None:
                    derived = ctl.solver_tolerance(name, change)
                    setattr(integrator, name, getattr(self._settings, name) if derived is None else derived)
            if integrator.traits.newton:  # Newton's linear solves: at least as tight as Newton asks
                integrator.cg_tol = min(self._settings.cg_tol, 1e-3 * integrator.newton_tol)
            done, _ = self._one_step(integrator, t)
            failure, estimate, order = None, None, 1
            if not done:
                failure = "divergence"
            elif integrator.traits.has_stats and not integrator.stats.converged:
                failure = "solver"
            else:
                x, v, rows = self._read_state(integrator)
                estimate, order = est.error(t + h, x, v, self._moved())
            kinks = ctl.kinks
            if ctl.judge(h, estimate, order, failure, t):
                if ctl.kinks > kinks:
                    est.points = est.points[-1:]  # the history before a kink does not help
                if landing:
                    integrator.clock = end
                self._sizes.append(h)
                self._current = (x, v, rows)
                est.push(integrator.clock, x, v)
                calm = h == ctl.tolerance.max_dt and estimate <= adaptive.CALM * ctl.bound(h)
                self._calm = self._calm + 1 if calm and self._batchable() else 0
                if not self._calm:
                    self._batch_size = adaptive.BATCH_FIRST
                return 1
            self._calm, self._batch_size = 0, adaptive.BATCH_FIRST
            self._back_to(integrator, kept)
            if ctl.dt < ctl.tolerance.min_dt:
                if failure is None:
                    cause = f"error estimate {estimate / ctl.bound(h):.3g} x its bound"
                else:
                    cause = "the state diverged" if failure == "divergence" else "the step's solve did not converge"
                tolerance = ctl.tolerance
                raise adaptive.StepSizeError(self._steps, t, ctl.dt, tolerance.min_dt, cause, self.integrator,
                                             None if self._min_dt_given else tolerance.horizon)
            if ctl.in_a_row >= adaptive.DROP_AFTER and len(est.points) > 1:
                est.points = est.points[-1:]  # a kink: the history before it does not help

    def _moved(self):
        """The particles (inner numbering) the passes changed the velocities of at the end
        of the step just taken (``Pass.moved``), None if no pass tells."""
        moved = [rows for rows in (p.moved() for p in self._passes) if rows is not None]
        return np.concatenate(moved) if moved else None

    def _back_to(self, integrator, kept):
        """Back to the state a rejected try started from (``_current``) and ``kept`` (``_kept``)."""
        x, v, rows = self._current
        self.restore(dataclasses.replace(kept, positions=self.to_user(x), velocities=self.to_user(v),
                                         carried=self._carried_of(integrator, rows, kept)))

    def _batchable(self) -> bool:
        """Whether calm steps may go in batches (``engine.adaptive``, "Batches"): an
        integrator held by its stability limit that keeps no per-step statistics, no pass
        between steps, no collider (whose impacts the estimate watches step by step), no
        gradient's record."""
        integrator = self._integrator
        return (integrator.traits.stability_limited and not integrator.traits.has_stats and not self._passes
                and not self._estimator.colliders and integrator.history is None)

    def _batch(self, integrator, end, stop, most) -> int:
        """Calm steps of ``max_dt`` in one launch, at most ``most`` and ``_batch_size`` of
        them, with room before ``end`` (s) for a landing after them, and up to the first
        past ``stop`` (s: a progress point of ``run_for``, not landed on); then
        ``order`` single steps whose states refill the estimate's history (``push``), as
        the steps one by one would have left it. Returns the steps accepted (0: no room,
        or the first step diverged; the caller tries it one by one)."""
        ctl, est = self._controller, self._estimator
        h, t = ctl.tolerance.max_dt, integrator.clock
        refill = est.order
        room = (end - t) / h - refill - 2 * adaptive.STRETCH if math.isfinite(end) else math.inf
        progress = math.ceil((stop - t) / h) if math.isfinite(stop) else math.inf
        span = adaptive.BATCH_SPAN * ctl.tolerance.horizon / h
        count = int(min(self._batch_size, most - refill, room, progress, span))
        if count < 2 or ctl.dt != h:
            self._calm = 0
            return 0
        if self._schedule is not None:
            self._schedule.apply(self._steps, t)
        integrator.dt = h
        self._bound_to(t + (count + refill) * h)
        done, _ = integrator.advance(count)
        self._steps += done
        self._sizes.extend([h] * done)
        ctl.accept_unjudged(h, done)
        self._current = self._read_state(integrator)
        est.reset(integrator.clock, *self._current[:2])
        if done < count:  # the step after diverged: tried one by one from here
            self._calm, self._batch_size = 0, adaptive.BATCH_FIRST
            return done
        for _ in range(refill):
            kept = self._kept()
            step, _ = self._one_step(integrator, integrator.clock)
            if not step:
                self._back_to(integrator, kept)
                self._calm, self._batch_size = 0, adaptive.BATCH_FIRST
                return done
            done += 1
            self._sizes.append(h)
            ctl.accept_unjudged(h, 1)
            self._current = self._read_state(integrator)
            est.push(integrator.clock, *self._current[:2])
        self._batch_size = min(2 * self._batch_size, adaptive.BATCH_MOST)
        self._calm = adaptive.CALM_TRIES - 1  # the next batch waits for a calm step tried and judged
        return done

    def _one_step(self, integrator, t=None):
        """One step of ``integrator.dt`` with the controls (from time t, s, in an
        error-controlled run) and the passes around it; counts it and its solver
        statistics if it was good. Returns (good steps: 0 or 1, ``divergence.verdict``)."""
        if self._schedule is not None:
            self._schedule.apply(self._steps, t)
        for p in self._passes:
            p.begin(integrator.state)
        self._bound_to(integrator.time_after())
        done, check = integrator.advance(1)
        if done and self._passes:
            integrator.settle()
            for p in self._passes:
                p.end(integrator.state, integrator.time)
            integrator.changed()
        self._steps += done
        if done and integrator.traits.has_stats:
            stats = integrator.stats
            self._cg_iterations.append(stats.iterations)
            self._cg_failures += not stats.converged
            if stats.newton_iterations is not None:
                self._newton_iterations.append(stats.newton_iterations)
                self._cuts += stats.cuts
        return done, check

    def _advance(self, integrator, n):
        """``n`` steps of ``integrator``: in launches of up to ``STEPS_PER_LAUNCH`` steps
        (cut at the control schedule's interval ends) when it keeps no per-step statistics
        and no strain limit or self-collision pass runs between steps, else one step at a
        time. Counts the good steps and the solver statistics; raises ``DivergenceError``
        at a failed step."""
        schedule = self._schedule
        if not integrator.traits.has_stats and not self._passes:
            while n:
                chunk = min(n, STEPS_PER_LAUNCH)
                if schedule is not None:
                    schedule.apply(self._steps)
                    chunk = min(chunk, schedule.steps_left(self._steps) or chunk)
                self._bound_to((self._steps + chunk) * self.dt)
                done, check = integrator.advance(chunk)
                self._steps += done
                self._raise_if_diverged(check)
                n -= chunk
            return
        for _ in range(n):
            _, check = self._one_step(integrator)
            self._raise_if_diverged(check)

    def _bound_to(self, t):
        """The divergence check's bound for states up to time ``t`` (s): with moving pins,
        ``base`` grown by what they can have put in (``pin_work``)."""
        if self._pin_work:
            base, gx0, factor = self._check
            self._integrator.dev.check[None] = (base + self._pin_work * t * t, gx0, factor)

    def _raise_if_diverged(self, check):
        code, kinetic, bound = check  # kinetic: the integrator's traits.checked_energy
        if code == divergence.OK:
            return
        failed = self._steps + 1
        integrator = self._integrator
        at = integrator.clock + integrator.dt if self._clocked else failed * self.dt
        raise DivergenceError(failed, at, divergence.CAUSES[code], kinetic, bound,
                              self.integrator, integrator.dt, integrator.traits.checked_energy)

    def energy(self) -> dict:
        """Kinetic, spring, each uniform force's potential and total energy (J) of the current
        state (``Model.energy``)."""
        return self._model.energy(self.positions, self.velocities)

    def info(self) -> dict:
        """What this run compiled and allocated: force terms, arrays and their bytes (with
        a multigrid hierarchy's: its level sizes in unknowns are "levels")."""
        integrator = self._open()
        terms = [term.name for term in active_terms(self._model)]
        if self._model.has_fixed:
            terms.append("fixed-filter")
        if self._model.has_moving_pins:
            terms.append("moving-pins")
        if self._model.has_colliders:
            kinds = sorted({c.kind for c in self._model.colliders}, key=list(COLLIDERS).index)
            terms.append("contact (" + ", ".join(kinds) + ")")
        terms += [p.term for p in self._passes if p.term is not None]
        if self._model.controls is not None:
            given = [name for name in ("pin_targets", "wind", "rest_lengths")
                     if getattr(self._model.controls, name) is not None]
            terms.append("controls (" + ", ".join(given) + ")")
        out = {"integrator": self.integrator, "precision": self.precision, "dt": self.dt,
               "particles": self._model.n_particles, "springs": self._model.n_springs,
               "terms": terms, "arrays": list(self._layout_names), "loops": self.loops,
               "preconditioner": self.preconditioner if integrator.traits.linear_solver else None,
               "newton": integrator.traits.newton, "bytes": self._bytes,
               "options": {option.name: getattr(self._settings, option.name) for option in integrator.options},
               "order": "given" if self._order is None else "z-order"}
        if self._controller is not None:
            out["tol"] = {name: getattr(self._settings, name) for name in ("tol", "min_dt", "max_dt", "horizon")}
        if integrator.traits.linear_solver:
            extra = integrator.preconditioner.describe()
            out["bytes"] += extra.pop("bytes")
            out.update(extra)
        return out

    def close(self):
        """Hand the run's fields back for reuse by the next Simulation (else done at garbage
        collection). Idempotent; any other call afterwards raises ``SimulationClosedError``."""
        self._release()
        self._integrator = None


def _option_property(option):
    return property(lambda self: getattr(self._settings, option.name),
                    doc=f"{', '.join(takers(option.name))}: {option.doc}.")


for _option in OPTIONS.values():
    setattr(Simulation, _option.name, _option_property(_option))


def _stats_property(kind):
    def stats(self):
        return next((p.stats() for p in self._passes if p.name == kind.name), None)
    return property(stats, doc=f"The {kind.name} pass's statistics (None without it): "
                               f"{textwrap.dedent(kind.stats.__doc__ or '').strip()}")


for _kind in PASSES.values():
    if _kind.stats_property:
        setattr(Simulation, _kind.stats_property, _stats_property(_kind))


def _option_docs() -> str:
    """The solver options' lines of ``Simulation``'s docstring."""
    lines = []
    for option in OPTIONS.values():
        values = " | ".join(f'"{c}"' for c in option.choices) if option.kind == "choice" else option.bounds
        lines.append(f"    {option.name} : {values}, default {option.described_default()}")
        lines += textwrap.wrap(f"{', '.join(takers(option.name))}: {option.doc}.", 84, initial_indent=" " * 8,
                               subsequent_indent=" " * 8)
    return "\n".join(lines) + "\n"


Simulation.__doc__ = Simulation.__doc__.replace("{options}", _option_docs()).replace(
    "{integrators}", " | ".join(f'"{name}"' for name in INTEGRATORS))


def _release(dev, integrator, passes):
    integrator.release()
    for p in passes:
        p.release()
    POOL.give(dev)


def _check_f32_range(model):
    for name in ("positions", "masses", "stiffness", "damping", "rest_lengths", "velocities", "gravity",
                 "pin_velocity", *model.term_parameters):
        values = np.abs(np.asarray(getattr(model, name)))
        if values.size and values.max() > F32_MAX_MAGNITUDE:
            raise ValueError(f"{name}: {values.max():g} is beyond what an f32 run holds "
                             f"(|value| <= {F32_MAX_MAGNITUDE:g}); use precision='f64'")
    if model.masses.min() < 1.0 / F32_MAX_MAGNITUDE:
        raise ValueError(f"masses: {model.masses.min():g} is below what an f32 run holds "
                         f"(>= {1.0 / F32_MAX_MAGNITUDE:g}); use precision='f64'")


def run(sim, steps=None, *, duration=None, frames=(), on_frame=None, progress=None):
    """Advance ``sim`` by ``steps`` steps, in chunks of at most 1/200 of the run; or by
    ``duration`` seconds (``run_for``).

    ``on_frame(sim)`` is called each time the steps taken here reach an entry of
    ``frames`` (sorted ints within 0..steps; 0 is before the first step), and
    chunks end there; ``progress(done, steps)`` after each chunk. A
    ``DivergenceError`` or ``KeyboardInterrupt`` propagates with ``sim`` at its last
    good state and every frame up to it delivered. Returns ``steps``.
    """
    if duration is not None:
        if steps is not None:
            raise ValueError("steps, duration: give one")
        return run_for(sim, duration, frames=frames, on_frame=on_frame, progress=progress)
    if steps is None:
        raise ValueError("steps: give steps or duration")
    steps = validate.count("steps", steps, low=0, high=MAX_STEPS)
    chunk = max(1, steps // 200)
    pending = iter(frames if on_frame is not None else ())  # read as the run goes: frames may be lazy
    upcoming = next(pending, None)
    done = 0
    while True:
        while upcoming is not None and upcoming <= done:
            if upcoming == done:
                on_frame(sim)
            upcoming = next(pending, None)
        if done >= steps:
            return steps
        k = min(chunk, steps - done)
        if upcoming is not None:
            k = min(k, int(upcoming) - done)
        sim.step(k)
        done += k
        if progress is not None:
            progress(done, steps)


SNAP = 1e-6  # a chunk's end this close (over the chunk) to a frame or the end is taken to be there


def run_for(sim, duration, *, frames=(), on_frame=None, progress=None):
    """Advance ``sim`` by ``duration`` s of simulated time (``Simulation.advance``), in
    chunks of 1/200 of it. ``frames``: sorted instants (s) within 0..duration from the
    run's start (0: before the first step), at which ``on_frame(sim)`` is called: an
    error-controlled run lands a step on each and on the end (on no chunk's end: a step
    may span chunks); a fixed-dt run's must be whole steps. ``progress(done, duration)``
    (s) after each chunk. Errors propagate as ``run``'s do.
    Returns the steps taken."""
    duration = validate.real_number("duration", duration, 0.0, ">=")
    first, start = sim.steps, sim.time
    pending = iter(frames if on_frame is not None else ())
    upcoming = next(pending, None)
    chunk = duration / 200
    done = 0.0
    while True:
        while upcoming is not None and upcoming <= done:
            if upcoming == done:
                on_frame(sim)
            upcoming = next(pending, None)
        if done >= duration:
            return sim.steps - first
        target = done + chunk
        if duration - target <= SNAP * chunk:
            target = duration
        if upcoming is not None and float(upcoming) - target <= SNAP * chunk:
            target = float(upcoming)  # not a sliver of a step short of it: the run lands there
        if sim.tol is None:
            sim.step(round((start + target) / sim.dt) - sim.steps)
            done = target
        else:  # steps land on the frames and the end only; a progress point is where the clock passed it
            landing = duration if upcoming is None else min(float(upcoming), duration)
            sim._advance_to(start + landing, start + target)
            done = landing if sim.time >= start + landing else max(target, sim.time - start)
        if progress is not None:
            progress(done, duration)
