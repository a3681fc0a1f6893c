"""Fit a model's parameters to recorded frames (``massspring fit``).

One factor per fitted parameter multiplies the model's own values (every spring's
stiffness by the same factor, and so on), and scipy's L-BFGS-B finds the factors that
minimise the mean squared distance between the recorded positions and those of a run
from the recording's first frame, with the gradient of that misfit in each factor from
``massspring.gradient`` (an adjoint run through every step): the factor's gradient is
the parameter's gradient summed against the model's values (the chain rule).

A recording is an export of ``massspring run --export DIR --format npz``: every frame a
state file with positions, velocities, the step and dt. The fit starts from the first
frame's state, steps with the recording's dt and compares the frames at their steps.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from massspring.support.extras import install_hint
from massspring.gradients import check_arguments, chosen_steps, gradient
from massspring.io.frames import read_frames
from massspring.io.state import read_state
from massspring.model import Model

FITTABLE = ("stiffness", "damping", "rest_lengths", "masses", "drag")  # scaled by one factor each
FACTOR_RANGE = (1e-3, 1e3)  # L-BFGS-B's bounds on every factor
MAX_ITER = 30  # L-BFGS-B iterations, default
STAGES = 2  # fits with error-controlled steps: steps chosen at the start, then again at the first fit's result
MAX_FIT_STEPS = 10**7  # steps of a fitted run at most: a frame past it is a damaged recording, not a fit
STATIONARY = 1e-6  # a stop with the projected gradient this far below its first is a converged fit


@dataclass(frozen=True)
class Recording:
    """Frames of one run: ``positions`` (F, n, 3) m at ``steps`` (F,) after the first
    frame (0 first, increasing), ``velocities`` (n, 3) m/s of the first, ``dt`` s."""

    positions: np.ndarray
    steps: np.ndarray
    velocities: np.ndarray
    dt: float
    directory: str


def check_params(params) -> tuple:
    """``params`` (names) checked against ``FITTABLE``: a ValueError naming the first
    unknown or repeated one."""
    params = tuple(params)
    if not params:
        raise ValueError(f"params: name at least one of {', '.join(FITTABLE)}")
    for name in params:
        if name not in FITTABLE:
            raise ValueError(f"params: {name!r} cannot be fitted; one of {', '.join(FITTABLE)}")
    if len(set(params)) != len(params):
        raise ValueError(f"params: {params} names a parameter twice")
    return params


def check_fit(model: Model, params, integrator) -> tuple:
    """``params`` (``check_params``), then the model, names and integrator as
    ``massspring.gradient`` checks them (its ValueErrors: "wrt", "model", "integrator")."""
    params = check_params(params)
    check_arguments(model, list(params), integrator)
    return params


def read_recording(directory, model: Model) -> Recording:
    """The npz frames of the export in ``directory``, each checked to be a state of
    ``model``'s size (ValueError naming the file otherwise), at least two, all with
    one dt and at increasing steps."""
    frames = read_frames(directory)
    if len(frames) < 2:
        raise ValueError(f"{directory}: {len(frames)} frame(s); a fit needs the first and at least one more")
    positions, steps, first, dt = [], [], None, None
    for frame in frames:
        path = Path(directory) / frame["file"]
        if path.suffix != ".npz":
            raise ValueError(f"{path}: not an npz frame; record with `massspring run ... --export DIR --format npz`")
        state = read_state(path, model, "the scene's model")
        if state.steps != frame["step"]:
            raise ValueError(f"{path}: step {state.steps}, where the export's list says {frame['step']}; is the "
                             f"recording damaged?")
        if first is None:
            first, dt = state, state.dt
        elif not math.isclose(state.dt, dt, rel_tol=1e-12):
            raise ValueError(f"{path}: dt {state.dt:g} s, the first frame's {dt:g} s; a fit needs one dt")
        elif state.steps <= steps[-1] + first.steps:
            raise ValueError(f"{path}: step {state.steps} is not after the frame before it")
        if state.steps - first.steps > MAX_FIT_STEPS:
            raise ValueError(f"{path}: step {state.steps} is {state.steps - first.steps:,} steps after the first "
                             f"frame's, more than a fit runs ({MAX_FIT_STEPS:,}); is the recording damaged?")
        positions.append(state.positions)
        steps.append(state.steps - first.steps)
    return Recording(np.array(positions), np.array(steps), first.velocities, float(dt), str(directory))


def fit_parameters(model: Model, recording: Recording, params, *, integrator, start=1.0, max_iter=MAX_ITER,
                   progress=None, tol=None, min_dt=None, max_dt=None, **options) -> dict:
    """The factors on ``model``'s ``params`` that make a run of it from the recording's
    first frame match its frames (module docstring).

    ``start``: every factor's first value; ``max_iter``: L-BFGS-B iterations at most;
    ``progress(iteration, factors, rms)`` after each; ``options``: the Simulation's
    solver options. ``tol`` (``min_dt``, ``max_dt``): the fit runs in ``STAGES``, each
    with the steps an error-controlled run of its starting factors takes to the
    recording's frames (``massspring.gradients.chosen_steps``), frozen
    (``gradient(dts=)``, whose misfit is smooth in the factors: steps chosen anew per run
    make it jump at tol's level, where L-BFGS-B's line search stalls); ``options``'
    newton_tol and cg_tol are the frozen runs'. Else steps of the recording's dt. Returns {"factors", "values" (each parameter's fitted mean),
    "rms_m" (the root mean square distance over the frames after the first), "iterations",
    "evaluations" (runs with their gradient), "converged", "message"}. Bad arguments
    raise ValueError before any step runs (``massspring.gradient`` checks the model
    and integrator before its run).
    """
    try:
        from scipy.optimize import minimize
    except ImportError:
        raise ValueError(f"fit: scipy is not installed ({install_hint('fit')})") from None
    params = check_fit(model, params, integrator)
    if not (FACTOR_RANGE[0] <= start <= FACTOR_RANGE[1]):
        raise ValueError(f"start: {start!r} is outside the factors' range {FACTOR_RANGE}")
    first = model.replaced(positions=recording.positions[0], velocities=recording.velocities)
    base = {name: np.asarray(getattr(first, name), dtype=np.float64) for name in params}
    used = np.arange(len(recording.steps))  # the run's frames are the recorded ones
    if tol is None:
        run = dict(steps=int(recording.steps[-1]), every=recording.steps[1:].astype(np.int64), dt=recording.dt)
    scaled = lambda factors: first.replaced(**{name: f * base[name] for name, f in zip(params, factors)})  # noqa: E731
    count = (len(recording.steps) - 1) * recording.positions[0].size

    def misfit(frames):
        diff = frames.positions[used] - recording.positions
        partial = np.zeros_like(frames.positions)
        partial[used] = diff / count
        return 0.5 * float(np.sum(diff * diff)) / count, {"positions": partial}

    values = {}  # factors -> misfit, for the progress line
    scale = []  # the misfit at the start: L-BFGS-B minimises misfit / scale (its tolerances are absolute)
    first_gradient = []  # the projected gradient at the start

    def value_and_gradient(factors):
        value, grads = gradient(scaled(factors), misfit, list(params), integrator=integrator, **run, **options)
        values[tuple(factors)] = value
        if not scale:
            scale.append(value if value > 0 else 1.0)
        slope = np.array([float(np.sum(grads[name] * base[name])) for name in params]) / scale[0]
        if not first_gradient:
            first_gradient.append(projected_norm(factors, slope))
        return value / scale[0], slope

    iteration = [0]

    def report(factors):
        iteration[0] += 1
        if progress is not None:
            progress(iteration[0], dict(zip(params, factors)), math.sqrt(2.0 * values.get(tuple(factors), math.nan)))

    at, evaluations = np.full(len(params), float(start)), 0
    for _ in range(1 if tol is None else STAGES):
        if tol is not None:  # steps chosen for the stage's start, then frozen: a smooth misfit to minimise
            times = recording.steps[1:] * recording.dt
            dts, frames = chosen_steps(scaled(at), integrator, tol, times, recording.dt, min_dt, max_dt, "f64",
                                       options)
            run = dict(dts=dts, every=frames[1:])
        result = minimize(value_and_gradient, at, jac=True, method="L-BFGS-B",
                          bounds=[FACTOR_RANGE] * len(params), callback=report,
                          options=dict(maxiter=max(max_iter - iteration[0], 1), ftol=0.0, gtol=1e-14))
        at, evaluations = result.x, evaluations + int(result.nfev)
    factors = {name: float(f) for name, f in zip(params, result.x)}
    converged, message = verdict(result, projected_norm(result.x, result.jac), first_gradient[0])
    return {"factors": factors, "values": {name: float(np.mean(base[name])) * factors[name] for name in params},
            "rms_m": math.sqrt(2.0 * float(result.fun) * scale[0]), "iterations": iteration[0],
            "evaluations": evaluations, "converged": converged, "message": message}


def projected_norm(factors, slope) -> float:
    """The norm of L-BFGS-B's projected gradient: ``slope`` without its components that
    point out of ``FACTOR_RANGE`` at a factor on its bound."""
    factors, slope = np.asarray(factors, dtype=np.float64), np.asarray(slope, dtype=np.float64)
    held = ((factors <= FACTOR_RANGE[0]) & (slope > 0)) | ((factors >= FACTOR_RANGE[1]) & (slope < 0))
    return float(np.linalg.norm(np.where(held, 0.0, slope)))


def verdict(result, last, first) -> tuple:
    """(converged, message) of an L-BFGS-B ``result`` whose projected gradient fell from
    ``first`` to ``last``. Its tolerances ask for more than the runs' precision, so a fit
    that reaches the recording usually ends with the line search unable to decrease the
    misfit (scipy's "ABNORMAL"): that stop counts as converged where the gradient is
    ``STATIONARY`` of its first or less, and is said to have failed otherwise."""
    ratio = last / first if first > 0 else 0.0
    said = str(result.message).strip().rstrip(":")
    if result.success:
        return True, f"converged ({said})"
    if ratio <= STATIONARY:
        return True, (f"converged: the misfit's gradient is {ratio:.1e} of its first, where the line search "
                      f"can no longer decrease it ({said})")
    if "ITERATIONS" in said.upper():  # scipy's "STOP: TOTAL NO. OF ITERATIONS REACHED LIMIT"
        return False, f"not converged: stopped at the iteration limit, gradient {ratio:.1e} of its first ({said})"
    return False, (f"not converged: the line search found no decrease with the gradient at {ratio:.1e} of its "
                   f"first ({said}): the misfit may have a kink there (a contact or self-collision switching) "
                   f"or the runs be solved too loosely for their gradient (tighten --cg-tol, --newton-tol)")
