"""Gradients of an objective of a run's frames, by the discrete adjoint of its steps.

``gradient(model, objective, wrt, steps=...)`` runs ``steps`` steps forward with the
run's own kernels, calls ``objective`` once on the recorded frames, then runs the
steps backwards: each integrator's ``adjoint`` (next to its forward kernels, e.g.
``kernels/euler.py``'s ``euler_adjoint``) turns dL/d(state after a step) into
dL/d(state before it) and adds the step's share of each parameter's gradient. The
result is the gradient of the run as computed (the discrete adjoint), not of the
differential equation.

Memory (checkpointing): a run whose every state fits in ``HISTORY_BYTES`` (256 MB)
keeps them all on the device. A longer one keeps the state at every
``checkpoint``-th step (by default about sqrt(steps) steps apart); the backward pass
runs each stretch between two kept states forward again from the earlier one into the
history, then backwards. Peak: about (steps / checkpoint + checkpoint) states of 48
bytes a particle, and one forward step more per step than the forward run.

Built (issue 39): the explicit, symplectic, RK4, linearised implicit, backward Euler,
BDF2 and implicit midpoint integrators, with springs, damping, gravity, drag and wind,
pins (fixed or moving, with their velocities' gradient), colliders: planes, spheres and
boxes with friction and restitution, self-collision (its pass's adjoint; every one of those
integrators), and controls over time (keyframed pins, wind, actuated rest lengths:
``ControlShares``). The adjoint kernels are compiled and their fields allocated only
when a gradient is asked for: a forward run is as before.
"""

from __future__ import annotations

import bisect
import dataclasses
import math
import warnings
from dataclasses import dataclass

import numpy as np
import taichi as ti

from massspring.support import memory
from massspring.support import validate
from massspring.support.validate import real_array
from massspring.support.defaults import MAX_STEPS
from massspring.device import POOL, Layout, capacity
from massspring.support.errors import GradientError, KinkWarning
from massspring.integrators import INTEGRATORS
from massspring.kernels import state as state_kernels
from massspring.model import Model, feedback, terms
from massspring.model import model as model_module
from massspring.model.controls import NAMES as CONTROL_NAMES
from massspring.engine.schedule import ControlShares
from massspring.engine.simulation import Simulation
from massspring.passes import for_model
from massspring.model.terms import active_terms

# The names ``wrt`` may hold, from the records of the terms and the Model (``terms.Gradient``:
# what each gradient is per, and its accumulator in the adjoint bundle) and the controls'
# arrays ("controls.<name>", per "control").
TERM_GRADIENTS = terms.gradients()
MODEL_GRADIENTS = {g.name: g for g in model_module.GRADIENTS}
PARAMETERS = {**{name: g.per for name, (g, _) in TERM_GRADIENTS.items()},
              **{name: g.per for name, g in MODEL_GRADIENTS.items()},
              **{f"controls.{name}": "control" for name in CONTROL_NAMES}}
PARTIALS = ("positions", "velocities")
STATE_BYTES = 48  # a particle's x and v in the history (float64)
HISTORY_BYTES = 256e6  # keep every state of a run whose history fits in this; else checkpoint


@dataclass(frozen=True)
class Frames:
    """The states an objective sees: ``positions`` (F, n, 3) m, ``velocities`` (F, n, 3)
    m/s in the model's particle numbering, ``times`` (F,) s, ``steps`` (F,) the step of
    each frame (frame 0 is the initial state, then every ``every``-th step)."""

    positions: np.ndarray
    velocities: np.ndarray
    times: np.ndarray
    steps: np.ndarray


def differentiable() -> tuple:
    """The integrators ``gradient`` can run backwards."""
    return tuple(name for name, cls in INTEGRATORS.items() if cls.traits.differentiable)


def gradient(model, objective, wrt, *, steps=None, every=1, integrator="symplectic", dt=1e-2, precision="f64",
             checkpoint=None, dts=None, tol=None, times=None, min_dt=None, max_dt=None, controller=None, **options):
    """The value of ``objective`` on a run of ``model`` and its gradient in ``wrt``.

    Parameters
    ----------
    model : Model
    objective : callable
        ``objective(frames)`` with a :class:`Frames`; returns ``(value, partials)``:
        a finite float and a dict holding "positions" and/or "velocities", arrays
        (F, n, 3) of dL/dX and dL/dV (an absent key is zero).
    wrt : str or sequence of str
        Names of ``PARAMETERS``: "stiffness", "damping", "rest_lengths" ((m,) per
        spring), "masses" ((n,)), "positions", "velocities" ((n, 3): the initial state;
        rows of pinned particles are zero), "gravity" ((3,)), "drag" (a float64
        scalar) and "wind" ((3,)) of a model with drag, "pin_velocity" ((k, 3), a row
        per pinned particle in the order of ``model.fixed``); of a model with
        ``controls`` (``massspring.Controls``), "controls.pin_targets",
        "controls.wind" and "controls.rest_lengths", shaped as those arrays; with a
        ``controller``, "controller.<name>" for each of its ``parameters`` (shaped as
        it), and not the controls it drives.
    steps : int >= 1
        Steps of ``dt`` (with ``dts``: len(dts), which it may repeat; with ``tol``: none).
    every : int >= 1, or increasing step numbers
        A frame at step 0 and at every ``every``-th step, or at step 0 and each of the
        given steps (1..steps).
    integrator : one of ``differentiable()``
    dt : float, s
        The step (with ``tol``: the first try).
    precision : "f64"
    checkpoint : int >= 1 or None
        Steps between kept states (None: about sqrt(steps)).
    dts : 1-D array of step sizes (s), optional
        Steps of these sizes (``Simulation.replay``: an error-controlled run's
        ``step_sizes``), frozen: the gradient of the run with those steps, their sizes
        constants.
    tol, times : float; increasing times (s) > 0, optional
        An error-controlled run (``Simulation(tol=tol, min_dt=, max_dt=, horizon=times[-1])``,
        its Newton and CG tolerances derived from tol) landing on each of ``times`` chooses the steps, then
        the gradient is that of ``dts`` = its ``step_sizes``, with frames at 0 and at
        ``times``; ``newton_tol``, ``cg_tol`` are the frozen run's.
    controller : ``massspring.Controller``, optional
        A feedback controller choosing the model's controls from the state
        (``Simulation(controller=)``); the gradient goes through it, by its ``vjp``, into
        its parameters and the states it read (not into pinned particles' rows, whose
        motion is then not differentiable: "pin_velocity" and "controls.pin_targets"
        are refused).
    **options : the Simulation's (``loops``, ...)

    Returns ``(value, grads)``: the float value and a dict of one float64 array per
    name in ``wrt``. Bad arguments raise ValueError naming them before any step runs.
    """
    if not callable(objective):
        raise ValueError(f"objective: expected a function of the frames, got {type(objective).__name__}")
    names = check_arguments(model, wrt, integrator, precision, controller)
    if controller is not None:
        options["controller"] = controller
    plan = _plan(model, integrator, steps, every, dt, precision, dts, tol, times, min_dt, max_dt, options)
    steps = plan.steps
    if checkpoint is None:
        checkpoint = default_checkpoint(model.n_particles, steps,
                                        STATE_BYTES + INTEGRATORS[integrator].kept_bytes(model))
    checkpoint = min(validate.count("checkpoint", checkpoint, low=1, high=MAX_STEPS), steps)
    memory.check(host_bytes(model, integrator, steps, len(plan.frames), checkpoint, controller is not None),
                 f"checkpoint: a gradient of {steps:,} steps of {model.n_particles:,} particles keeping a state every "
                 f"{checkpoint:,} steps and {len(plan.frames):,} frames (give a larger checkpoint or every)")

    if plan.sizes is not None and model.controls is not None:
        dt = model.controls.interval  # a dt the controls accept; ``replay`` sets each step's size
    sim = Simulation(model, integrator, dt=dt, precision=precision, **options)
    if plan.sizes is not None:
        sim.replay(plan.sizes[:0])  # the clock runs from the start: the kept states carry what it needs
    _warn_at_a_kink(sim)
    adj = None
    try:
        adj = _adjoint_bundle(sim, checkpoint)
        backward = [b for b in (p.adjoint(sim, adj) for p in sim.passes) if b is not None]  # run back where they acted
        frames, kept, last = _forward(sim, adj, plan, checkpoint, backward)
        if sim.schedule is not None:
            sim.schedule.freeze()  # runs again from kept states take the controls chosen
        value, partials = _call(objective, frames, model.n_particles)
        driven = controller is not None and "pin_targets" in controller.drives  # the pins' motion goes back
        wants = Wants(masses="masses" in names, rate_gradient="damping" in names and not model.has_damping,
                      pins="pin_velocity" in names or "controls.pin_targets" in names or driven,
                      friction=model.has_friction and INTEGRATORS[integrator].traits.linear_solver)
        shares = ControlShares(sim, adj) if model.controls is not None else None
        with np.errstate(over="ignore", invalid="ignore"):  # an overflow is refused below, by name
            _backward(sim, adj, wants, partials, plan, kept, last, checkpoint, shares, backward)
            grads = _read(sim, adj, names, shares)
        for b in backward:
            b.add_gradients(grads)
        for name, grad in grads.items():
            if not np.all(np.isfinite(grad)):
                raise ValueError(f"objective: its partials (largest magnitude {_largest(partials):.3g}) made the "
                                 f"gradient in {name!r} overflow; scale the objective down")
        return value, grads
    finally:
        sim.close()
        if adj is not None:
            POOL.give(adj)


AT_REST = 1e-12  # |l / l0 - 1| of a spring this close to its rest length is at the clamp's kink


def _warn_at_a_kink(sim):
    """A ``KinkWarning`` when ``sim`` solves with the definiteness fix and some of its
    model's springs start at their rest length (|l / l0 - 1| <= ``AT_REST``), where the
    fix's clamp of the transverse stiffness, max(0, 1 - l0 / l), has a kink: the gradient
    there is one side's (measured on the cloth scene's start state: -0.1625 where one-sided
    differences gave -0.0947 and -0.1478)."""
    if not getattr(sim.settings, "definiteness_fix", False) or not INTEGRATORS[sim.integrator].traits.linear_solver:
        return
    model = sim.model
    springs, rest = model.springs, model.rest_lengths
    if not len(springs):
        return
    length = np.linalg.norm(model.positions[springs[:, 1]] - model.positions[springs[:, 0]], axis=1)
    at_rest = int(np.count_nonzero((rest > 0) & (np.abs(length - rest) <= AT_REST * rest)))
    if at_rest:
        warnings.warn(f"gradient: {at_rest:,} of {len(springs):,} springs start at their rest length, where the "
                      f"definiteness fix's clamp has a kink: the gradient there is one side's and central "
                      f"differences straddle it (docs/gradients.md); give definiteness_fix=False, or start off "
                      f"the rest lengths", KinkWarning, stacklevel=3)


@dataclass(frozen=True)
class Plan:
    """A gradient's run: ``steps``; ``frames`` the steps of its frames (0 first,
    increasing); ``sizes`` (steps,) s of a replayed run's steps, None for steps of dt;
    ``times`` (steps + 1,) s, the time of each state of a replayed run (None)."""

    steps: int
    frames: np.ndarray
    sizes: np.ndarray | None = None
    times: np.ndarray | None = None

    def next_frame(self, k) -> int:
        """The first frame's step after step k (``steps`` after the last)."""
        i = int(np.searchsorted(self.frames, k, side="right"))
        return int(self.frames[i]) if i < len(self.frames) else self.steps

    def is_frame(self, k) -> bool:
        i = int(np.searchsorted(self.frames, k))
        return i < len(self.frames) and int(self.frames[i]) == k

    def step(self, k) -> tuple:
        """(clock, size, before) of step k of a replayed run (``Integrator.at_step``), else Nones."""
        if self.sizes is None:
            return None, None, None
        return float(self.times[k]), float(self.sizes[k]), float(self.sizes[k - 1]) if k else None

    def time(self, k):
        """The time (s) of the state after k steps of a replayed run (None: k dt)."""
        return None if self.times is None else float(self.times[k])


def _plan(model, integrator, steps, every, dt, precision, dts, tol, times, min_dt, max_dt, options) -> Plan:
    """The run ``gradient``'s arguments ask for (ValueError naming the argument); with
    ``tol``, after the error-controlled run that chooses its steps."""
    if tol is not None or times is not None:
        for name, value, unset in (("tol", tol, None), ("times", times, None)):
            if value is unset:
                raise ValueError(f"{name}: an error-controlled gradient needs tol and times (the frames' times, s)")
        for name, value, unset in (("steps", steps, None), ("dts", dts, None), ("every", every, 1)):
            if value is not unset and not (name == "every" and isinstance(value, int) and value == 1):
                raise ValueError(f"{name}: with tol the run chooses its steps and has its frames at times; "
                                 f"give {name} or tol, not both")
        times = real_array("times", times)
        if times.ndim != 1 or not times.size or not np.all(np.isfinite(times)) or times[0] <= 0 \
                or np.any(np.diff(times) <= 0):
            raise ValueError("times: expected increasing finite times (s), the first > 0")
        dts, frames = chosen_steps(model, integrator, tol, times, dt, min_dt, max_dt, precision, options)
        return _replayed(dts, frames)
    for name, value in (("min_dt", min_dt), ("max_dt", max_dt)):
        if value is not None:
            raise ValueError(f"{name}: only with tol (an error-controlled run chooses the steps)")
    if dts is not None:
        dts = real_array("dts", dts)
        if dts.ndim != 1 or not dts.size or not np.all(np.isfinite(dts)) or np.any(dts <= 0):
            raise ValueError("dts: expected a 1-D array of step sizes (s), each finite and > 0")
        if steps is not None and validate.count("steps", steps, low=1, high=MAX_STEPS) != dts.size:
            raise ValueError(f"steps: {steps} is not len(dts) = {dts.size}")
        validate.count("dts", dts.size, low=1, high=MAX_STEPS)
        return _replayed(dts, _frame_steps(every, dts.size))
    if steps is None:
        raise ValueError("steps: give the number of steps (or dts, or tol and times)")
    steps = validate.count("steps", steps, low=1, high=MAX_STEPS)
    return Plan(steps, _frame_steps(every, steps))


def _replayed(dts, frames) -> Plan:
    times = np.concatenate(([0.0], np.cumsum(dts)))  # summed in order, as the run's clock is
    return Plan(int(dts.size), frames, np.ascontiguousarray(dts, dtype=np.float64), times)


def _frame_steps(every, steps) -> np.ndarray:
    """The frames' steps: 0 and every ``every``-th step, or 0 and the given steps."""
    try:
        at = np.asarray(every)
    except ValueError:  # ragged nesting
        at = np.zeros((0, 0))
    if at.ndim == 0:
        every = validate.count("every", every, low=1, high=MAX_STEPS)
        return np.arange(0, steps + 1, every)
    if at.ndim != 1 or not at.size or at.dtype.kind not in "iu" or at[0] < 1 or at[-1] > steps \
            or np.any(np.diff(at) <= 0):
        raise ValueError(f"every: expected a step count or increasing step numbers within 1..{steps}, got {every!r}")
    return np.concatenate(([0], at)).astype(np.int64)


def chosen_steps(model, integrator, tol, times, dt, min_dt, max_dt, precision, options):
    """The step sizes (s) an error-controlled run of ``model`` takes to ``times[-1]``,
    landing on each of ``times``, and the steps of its frames (0 and one per time). Its
    Newton and CG tolerances are derived from ``tol`` (``newton_tol``, ``cg_tol`` of
    ``options`` are the frozen run's)."""
    from massspring.engine.simulation import run_for

    own = {name: value for name, value in options.items() if name not in ("newton_tol", "cg_tol")}
    sim = Simulation(model, integrator, dt=dt, precision=precision, tol=tol, min_dt=min_dt, max_dt=max_dt,
                     horizon=float(times[-1]), **own)
    at = [0]
    try:
        run_for(sim, float(times[-1]), frames=times.tolist(), on_frame=lambda s: at.append(s.steps))
        return sim.step_sizes, np.array(at, dtype=np.int64)
    finally:
        sim.close()


def check_bridge(model, policy, run):
    """A bridge's (``massspring.jax``, ``massspring.torch``) arguments that are
    ``gradient``'s: ``model``, a ``policy`` (None or given) that needs the model's
    controls, and ``run`` without the keywords the bridge sets. ValueError naming them."""
    if not isinstance(model, Model):
        raise ValueError(f"model: expected a massspring.Model, got {type(model).__name__}")
    if policy is not None and model.controls is None:
        raise ValueError("policy: the model has no controls; give it Controls with the intervals and the "
                         "rest lengths, wind or pin targets the policy sets")
    for name in ("objective", "wrt", "controller"):
        if name in run:
            raise ValueError(f"{name}: the bridge sets it (the loss, the policy's parameters and the physics, "
                             f"the policy)")


def with_parameters(model, values) -> Model:
    """``model`` with the arrays of ``values`` (names of ``PARAMETERS`` -> arrays) in place of
    its own, "controls.<name>" in its ``Controls``; checked as any Model is."""
    controls = {name.split(".", 1)[1]: value for name, value in values.items() if name.startswith("controls.")}
    own = {name: value for name, value in values.items() if not name.startswith("controls.")}
    if controls:
        if model.controls is None:
            raise ValueError(f"{next(iter(controls))!r}: the model has no controls")
        own["controls"] = dataclasses.replace(model.controls, **controls)
    return model.replaced(**own) if own else model


def check_arguments(model, wrt, integrator, precision="f64", controller=None) -> list:
    """The names of ``wrt``, once ``model``, ``wrt``, ``integrator``, ``precision`` and
    ``controller`` are checked as ``gradient`` checks them (a ValueError naming the
    argument otherwise)."""
    if controller is not None and isinstance(model, Model):
        feedback.check(controller, model.controls)
    names = _check_wrt(wrt, model, controller)
    validate.choice("integrator", integrator, tuple(INTEGRATORS))
    if not INTEGRATORS[integrator].traits.differentiable:
        raise ValueError(f"integrator: gradients through {integrator!r} steps are not built yet; "
                         f"they are for: {', '.join(differentiable())}")
    if precision != "f64":
        raise ValueError(f"precision: gradients are computed in f64 only, got {precision!r}")
    terms = [term.name for term in active_terms(model) if not term.kernel.differentiable]
    passes = [kind.refusal or kind.name for kind in for_model(model) if not kind.differentiable]
    for feature, present in ((" and ".join(passes), bool(passes)), (" and ".join(terms), bool(terms))):
        if present:
            raise ValueError(f"model: gradients through {feature} are not built yet (issue 39); "
                             f"a model of springs, damping, gravity, drag, pins and colliders has them")
    return names


@dataclass(frozen=True)
class Wants:
    """Compile-time switches of an adjoint kernel: ``masses``: add the masses' gradient
    (needs the step's forces again); ``rate_gradient``: add the damping coefficients'
    gradient in a model without a damping term; ``pins``: add the pin velocities'
    gradient; ``friction``: friction after a solve (the implicit integrators' with a collider
    with friction: ``friction.friction_adjoint``)."""

    masses: bool
    rate_gradient: bool
    pins: bool = False
    friction: bool = False


def history_stride(n) -> int:
    """Rows a state of n particles takes in the history (a capacity class, so that models
    of nearby sizes share a bundle and its compiled kernels)."""
    return capacity(n, 64)


def host_bytes(model, integrator, steps, frames, checkpoint, feedback=False) -> int:
    """Bytes a gradient holds in numpy beside its fields: the states kept at the starts of
    its stretches of ``checkpoint`` steps but the last (``_forward``, with what the
    integrator carries), the ``frames`` the objective sees, what the passes' runs
    backwards hold (``Pass.gradient_bytes``) and, with a ``feedback`` controller, the
    state it read at each interval (``Simulation.control_states``)."""
    n = model.n_particles
    kept = (steps - 1) // checkpoint * (STATE_BYTES + INTEGRATORS[integrator].kept_bytes(model)) * n
    passes = sum(kind.gradient_bytes(model, checkpoint, integrator) for kind in for_model(model))
    read = model.controls.intervals * STATE_BYTES * n if feedback else 0
    return kept + frames * STATE_BYTES * n + passes + read


def default_checkpoint(n, steps, state_bytes=STATE_BYTES) -> int:
    """Every state kept if the history of all ``steps`` (``state_bytes`` a particle a state)
    fits in ``HISTORY_BYTES``, else about sqrt(steps) between kept states (``steps / k + k``
    states held)."""
    if capacity(steps + 1, 8) * history_stride(n) * state_bytes <= HISTORY_BYTES:
        return steps
    return math.isqrt(steps - 1) + 1


def _check_wrt(wrt, model, controller=None):
    names = [wrt] if isinstance(wrt, str) else list(wrt) if isinstance(wrt, (list, tuple)) else None
    if not isinstance(model, Model):
        raise ValueError(f"model: expected a massspring.Model, got {type(model).__name__}")
    if not names or not all(isinstance(name, str) for name in names):
        raise ValueError(f"wrt: expected a name or a list of names of {', '.join(PARAMETERS)}, got {wrt!r}")
    own = {} if controller is None else {f"controller.{p}" for p in controller.parameters}
    for name in names:
        if name in own:
            continue
        if name not in PARAMETERS:
            more = "" if controller is None else ", " + ", ".join(sorted(own))
            raise ValueError(f"wrt: unknown parameter {name!r}; expected some of {', '.join(PARAMETERS)}{more}")
        if controller is not None and (name in ("pin_velocity", "controls.pin_targets")
                                       or name.startswith("controls.") and name[9:] in controller.drives):
            raise ValueError(f"wrt: {name!r}: with a feedback controller, "
                             + ("pins' motion is not differentiated (the controller's derivative in pinned "
                                "particles' state is dropped)" if "pin" in name else
                                "the controller sets it; ask for its parameters (controller.<name>)"))
        if PARAMETERS[name] == "spring" and model.n_springs == 0:
            raise ValueError(f"wrt: {name!r}: the model has no springs")
        if name == "pin_velocity" and not model.has_fixed:
            raise ValueError("wrt: 'pin_velocity': the model has no pins (fixed)")
        if name in TERM_GRADIENTS:
            record, term = TERM_GRADIENTS[name]
            if record.absent and not term.active(model):
                raise ValueError(f"wrt: {name!r}: the model has no {record.absent}")
        if PARAMETERS[name] == "control":
            array = name.split(".", 1)[1]
            if model.controls is None or getattr(model.controls, array) is None:
                raise ValueError(f"wrt: {name!r}: the model has no {name} (Model(controls=Controls({array}=...)))")
        overridden = {"wind": "wind", "pin_velocity": "pin_targets"}.get(name)
        if overridden and model.controls is not None and getattr(model.controls, overridden) is not None:
            raise ValueError(f"wrt: {name!r}: the model's controls.{overridden} set it over time; "
                             f"ask for 'controls.{overridden}'")
    if len(set(names)) != len(names):
        raise ValueError(f"wrt: a name given twice in {names}")
    return names


def _forward(sim, adj, plan, checkpoint, backward=()):
    """Run ``plan``'s steps: the frames; the states (numpy, with what the integrator carries:
    BDF2's previous state) at the starts of the stretches of
    ``checkpoint`` steps but the last, whose states (its end's too) go to the history as
    the run passes them (and to each of ``backward``, the passes' adjoints, its steps'
    records); the start of that last stretch."""
    n, stride = sim.model.n_particles, int(adj.stride[None])
    integrator = sim.stepper
    steps = plan.steps
    last = (steps - 1) // checkpoint * checkpoint
    for b in backward:
        b.start(last)
    positions, velocities, at, kept = [], [], [], {}
    done = 0
    while True:
        if done < last and done % checkpoint == 0:
            kept[done] = (sim.positions, sim.velocities, sim.carried_state())
        if done >= last:
            integrator.keep(adj, done - last)
        if plan.is_frame(done):
            positions.append(sim.positions)
            velocities.append(sim.velocities)
            at.append(done)
        if done == steps:
            break
        if done >= last and integrator.records_history:  # the last stretch in launches that record it
            _recorded(sim, adj, last, plan, done, steps - done)
            frames = plan.frames[plan.frames > done]
            xs, vs = np.empty((len(frames), n, 3)), np.empty((len(frames), n, 3))
            if len(frames):
                state_kernels.read_states(adj.hx, adj.hv, (frames - last).astype(np.int32), xs, vs, n, stride)
            for k, x, v in zip(frames, xs, vs):
                positions.append(sim.to_user(x))
                velocities.append(sim.to_user(v))
                at.append(int(k))
            break
        stop = done + 1 if done >= last else min(plan.next_frame(done), last, (done // checkpoint + 1) * checkpoint)
        if done >= last:
            _recorded(sim, adj, last, plan, done, stop - done)
        else:
            _take(sim, plan, done, stop - done)
        done = stop
    at = np.array(at)
    times = at * sim.dt if plan.times is None else plan.times[at]
    return Frames(np.array(positions), np.array(velocities), times, at), kept, last


def _take(sim, plan, start, count):
    """``count`` steps of ``plan`` from step ``start``."""
    if plan.sizes is None:
        sim.step(count)
    else:
        sim.replay(plan.sizes[start:start + count])


def _recorded(sim, adj, first, plan, start, count):
    """``_take`` with the integrator recording into ``adj``'s history, whose slot 0
    is the state after step ``first`` (``Integrator.history``)."""
    integrator = sim.stepper
    integrator.history = (adj, first)
    try:
        _take(sim, plan, start, count)
    finally:
        integrator.history = None


def _call(objective, frames, n):
    """``objective(frames)``, its value and partials checked."""
    out = objective(frames)
    if not (isinstance(out, tuple) and len(out) == 2):
        raise ValueError(f"objective: expected a (value, partials) pair, got {type(out).__name__}")
    value, partials = out
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"objective: the value must be a number, got {type(value).__name__}") from None
    if not math.isfinite(value):
        raise ValueError(f"objective: the value is {value}, not a finite number")
    if not isinstance(partials, dict):
        raise ValueError(f"objective: partials must be a dict with keys of {PARTIALS}, got {type(partials).__name__}")
    shape = frames.positions.shape
    out = {}
    for key, arr in partials.items():
        if key not in PARTIALS:
            raise ValueError(f"objective: unknown partials key {key!r}; expected some of {PARTIALS}")
        try:
            arr = np.asarray(arr)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"objective: partials[{key!r}] is not an array of numbers ({exc})") from None
        if arr.dtype.kind == "c":
            raise ValueError(f"objective: partials[{key!r}] holds complex values; give real derivatives")
        if arr.dtype.kind not in "biuf":
            raise ValueError(f"objective: partials[{key!r}] holds {arr.dtype} values, not numbers")
        arr = arr.astype(np.float64)
        if arr.shape != shape:
            raise ValueError(f"objective: partials[{key!r}] has shape {arr.shape}, expected {shape} (frames, n, 3)")
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"objective: partials[{key!r}] holds a value that is not finite")
        out[key] = arr
    zero = np.zeros(shape)
    return value, (out.get("positions", zero), out.get("velocities", zero))


def _largest(partials) -> float:
    return max(float(np.abs(p).max(initial=0.0)) for p in partials)


def _adjoint_bundle(sim, checkpoint):
    """The fields of the backward pass (float64; see ``euler.euler_adjoint``), with a
    history of the ``checkpoint`` + 1 states of a stretch, its end's included (``hx``,
    ``hv``: slots of ``stride`` rows; an implicit step's adjoint reads the state after it)."""
    n, m = sim.model.n_particles, sim.model.n_springs
    layout = Layout(n, m, ti.f64)
    stride = history_stride(n)
    layout.add("stride", ti.i32, (), values=np.array(stride))
    rows = capacity(checkpoint + 1, 8) * stride
    for name in ("hx", "hv"):
        layout.vectors(name, ti.f64, rows)
    for name in ("lx", "lv"):
        layout.vectors(name, ti.f64, values=np.zeros((n, 3)))
    layout.vectors("w", ti.f64, values=np.zeros((n, 3)))
    layout.add("gm", ti.f64, "particle", values=np.zeros(n))
    for name in ("sx", "sv"):
        layout.vectors(name, ti.f64, "spring")
    for name in ("px", "pv", "gp"):
        layout.vectors(name, ti.f64, values=np.zeros((n, 3)))
    for record, _ in TERM_GRADIENTS.values():  # the terms' accumulators
        if record.per == "vector":
            layout.vectors(record.field, ti.f64, values=np.zeros((n, 3)))
        elif record.per == "spring":
            layout.add(record.field, ti.f64, "spring", values=np.zeros(m) if m else None)
        else:
            layout.add(record.field, ti.f64, "particle", values=np.zeros(n))
    if sim.model.has_colliders:
        layout.vectors("cx", ti.f64)  # the contact response's gradient in the step's start position
    INTEGRATORS[sim.integrator].declare_adjoint(layout, sim.model, stride, rows)
    for kind in for_model(sim.model):
        kind.declare_adjoint(layout, sim.model)
    return layout.allocate(f"model: {n:,} particles and {m:,} springs; the fields of its gradient "
                           f"with {checkpoint:,} states kept (give a smaller checkpoint)")


def _backward(sim, adj, wants, partials, plan, kept, last, checkpoint, shares=None, backward=()):
    """Run the steps backwards, stretch by stretch: each but the last run again from its
    kept state into the history first; ``shares`` (a ``ControlShares``) collects the
    controls' gradients; ``backward`` (the passes' adjoints, ``Pass.adjoint``) run the
    passes backwards in the steps where they acted."""
    integrator, n, steps = sim.stepper, sim.model.n_particles, plan.steps
    frame_of = {int(k): f for f, k in enumerate(plan.frames)}
    ordered = sorted(frame_of)

    def add_frame(k, lx, lv):
        f = frame_of[k]
        lx = lx + sim.to_inner(partials[0][f])
        lv = lv + sim.to_inner(partials[1][f])
        state_kernels.load_vectors(adj.lx, np.ascontiguousarray(lx))
        state_kernels.load_vectors(adj.lv, np.ascontiguousarray(lv))

    if steps in frame_of:
        add_frame(steps, np.zeros((n, 3)), np.zeros((n, 3)))
    for start in reversed(range(0, steps, checkpoint)):
        end = min(start + checkpoint, steps)
        if start != last:
            for b in backward:
                b.start(start)
            positions, velocities, carried = kept[start]
            sim.set_state(positions, velocities, steps=start, carried=carried, time=plan.time(start))
            for k in range(start, end + 1):
                if k > start:
                    _recorded(sim, adj, start, plan, k - 1, 1)
                integrator.keep(adj, k - start)
        k = end - 1
        while k >= start:
            below = bisect.bisect_right(ordered, k) - 1  # down to the last frame's step at or before k
            low = max(ordered[below], start) if below >= 0 else start
            if shares is not None and plan.sizes is None:  # and to the first step of k's control interval
                low = max(low, k - k % shares.schedule.per)
            plain = not any(b.any_in(low, k) for b in backward)
            batch = plain and plan.sizes is None and k > low
            if batch and shares is not None:
                shares.schedule.apply(k)  # the interval's values, for all the steps down to low
            if batch and integrator.adjoint_steps(adj, k - start, k - low + 1, wants):
                k = integrator.steps = low
                if shares is not None:
                    shares.after(k)
            else:
                integrator.at_step(k, *plan.step(k))  # the step's start time (moving colliders) and size
                if shares is not None:
                    shares.schedule.apply(k, plan.time(k))
                acted = [b.before(k, k - start) for b in reversed(backward)]
                stats = integrator.adjoint(adj, k - start, wants)
                if stats is not None and not stats.converged:
                    raise GradientError(k, stats.reason, stats.residual, sim.integrator)
                for b, done in zip(reversed(backward), acted):
                    if done is not None:
                        b.after(done, wants)
                if shares is not None:
                    shares.after(k, plan.time(k), plan.time(k - 1) if k else None)
            if k in frame_of:
                add_frame(k, adj.read("lx", n), adj.read("lv", n))
            k -= 1


def _read(sim, adj, names, shares=None):
    """The gradients asked for, in the user's numbering (a rest length the controls set
    over time has none of its own: zero)."""
    model, order = sim.model, sim.numbering
    n, m = model.n_particles, model.n_springs
    controlled = {} if shares is None else shares.gradients(adj.read("lv", n))

    def springs(field):
        inner = adj.read(field, m)
        if order is None:
            return inner
        out = np.empty_like(inner)
        out[order.springs] = inner
        return out

    grads = {}
    for name in names:
        if name in ("positions", "velocities"):
            rows = sim.to_user(adj.read("lx" if name == "positions" else "lv", n))
            rows[model.fixed] = 0.0
            grads[name] = rows
        elif name == "masses":
            grads[name] = sim.to_user(adj.read("gm", n))
        elif name == "pin_velocity":  # the steps' shares, and the initial velocity's (a pin starts at vp)
            grads[name] = sim.to_user(adj.read("gp", n) + adj.read("lv", n))[model.fixed]
        elif name in controlled:
            grads[name] = controlled[name]
        else:
            record = TERM_GRADIENTS[name][0]
            if record.per == "spring":
                grads[name] = springs(record.field)
            elif record.per == "vector":
                grads[name] = adj.read(record.field, n).sum(axis=0)
            elif record.per == "scalar":
                grads[name] = np.float64(adj.read(record.field, n).sum())
            else:
                grads[name] = sim.to_user(adj.read(record.field, n))
            if name == "rest_lengths" and model.controls is not None and model.controls.springs is not None:
                grads[name][model.controls.springs] = 0.0
    return grads
