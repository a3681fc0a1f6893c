"""Feedback controls: a controller that chooses each control interval's values from the
state the run is in when it enters the interval (closed loop), and its vector-Jacobian
product, so that ``massspring.gradient`` differentiates through it.

A model's ``Controls`` give the intervals (``interval`` s each, S of them), the actuated
``springs`` and which controls there are; a :class:`Controller` given to the run
(``Simulation(..., controller=)``, ``gradient(..., controller=)``) replaces the values of
the controls it ``drives`` ("rest_lengths": (c,) m of the actuated springs, "wind": (3,)
m/s, "pin_targets": (k, 3) m, where the pins are at the interval's end, a row per pin in
the order of ``Model.fixed``) for interval s < S by ``controller.controls(state)``, called
once as the run enters interval s, with the state at the interval's start
(:class:`ControlState`: positions and velocities (n, 3) in the model's numbering, time
s T). After the last interval the last values hold, as open-loop controls do (pins stand
at their last targets). A pin moves to the target chosen for an interval at a constant
velocity over it, as keyframed pins do; at the start it has the model's pin velocity
(its controls' first interval's, the values before the controller chooses).

In a gradient's backward pass, once the adjoint has reached the start of interval s, the
objective's derivative in that interval's values, c_s (``cotangents``), goes through
``controller.vjp(state, cotangents)``: its parameters' share (dL/dtheta += c_s du/dtheta)
and the state's (dL/dx_s += c_s du/dx, dL/dv_s += c_s du/dv). Rows of pinned particles
go back through the pins' motion when the controller drives the pins; otherwise they are
dropped (a pin's state is then the run's, not a free variable).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

DRIVEN = ("rest_lengths", "wind", "pin_targets")  # the controls a controller may drive


@dataclass(frozen=True, eq=False)
class ControlState:
    """What a controller reads at the start of interval ``interval``: ``positions`` (n, 3)
    m and ``velocities`` (n, 3) m/s in the model's particle numbering, ``time`` s."""

    positions: np.ndarray
    velocities: np.ndarray
    time: float
    interval: int


class Controller:
    """Base of feedback controllers: subclass it, set ``interval`` (s), ``drives`` (a tuple
    of ``DRIVEN`` names), ``springs`` ((c,) the actuated springs, with "rest_lengths") and
    ``parameters`` (name -> float64 array, updated in place by whoever trains it), and
    define ``controls`` and ``vjp``.

    ``controls(state)`` returns a dict holding, for each name of ``drives``, the
    interval's values: "rest_lengths" (c,) m (>= 0), "wind" (3,) m/s, "pin_targets" (k, 3) m.
    ``vjp(state, cotangents)`` takes dL/d(those values) (same keys and shapes) and
    returns ``(parameters, positions, velocities)``: dL/d(each parameter) as a dict of
    arrays shaped like them, and dL/dx, dL/dv (n, 3) of the state, each the transpose of
    ``controls``'s Jacobian at ``state`` applied to the cotangents.
    """

    interval: float
    drives: tuple = ()
    springs: np.ndarray | None = None
    parameters: dict

    def controls(self, state: ControlState) -> dict:
        raise NotImplementedError

    def vjp(self, state: ControlState, cotangents: dict) -> tuple:
        raise NotImplementedError

    def top_speed(self):
        """The fastest (m/s) the controls it sets can drive the particles, for the run's
        divergence check (its floor counts it as it counts ``Controls.speeds``): a wind's
        speed, or an actuated rest length's largest change over an interval by the
        interval. None (the default): unknown; the check then counts the model's controls'
        values as given."""
        return None


def top_speed(controller) -> float:
    """``controller.top_speed()`` checked (0 for no controller or an unknown speed)."""
    if controller is None:
        return 0.0
    speed = controller.top_speed()
    if speed is None:
        return 0.0
    speed = float(speed)
    if not np.isfinite(speed) or speed < 0:
        raise ValueError(f"controller.top_speed: expected a finite speed >= 0 m/s or None, got {speed!r}")
    return speed


def check(controller, controls) -> None:
    """``controller`` against a model's ``controls`` (``massspring.Controls`` or None):
    ValueError naming what disagrees."""
    if not isinstance(controller, Controller):
        raise ValueError(f"controller: expected a massspring.Controller, got {type(controller).__name__}")
    if controls is None:
        raise ValueError("controller: the model has no controls; give it Controls with the intervals and "
                         "the controls the controller drives (e.g. SineNetwork.controls_for)")
    drives = tuple(controller.drives)
    if not drives or any(name not in DRIVEN for name in drives) or len(set(drives)) != len(drives):
        raise ValueError(f"controller.drives: expected distinct names of {', '.join(DRIVEN)}, got {drives!r}")
    if not np.isclose(float(controller.interval), controls.interval, rtol=1e-12, atol=0):
        raise ValueError(f"controller.interval: {controller.interval!r} s is not the model's controls.interval "
                         f"{controls.interval!r} s")
    for name in drives:
        if getattr(controls, name) is None:
            raise ValueError(f"controller.drives: {name!r}, but the model's controls have no {name}")
    if "rest_lengths" in drives:
        springs = np.asarray(controller.springs)
        if springs.shape != controls.springs.shape or np.any(springs != controls.springs):
            raise ValueError("controller.springs: not the model's controls.springs (the same actuated springs, "
                             "in the same order)")
    params = getattr(controller, "parameters", None)
    if not isinstance(params, dict) or not all(isinstance(k, str) for k in params):
        raise ValueError("controller.parameters: expected a dict of name -> array")


def outputs(controller, state, controls) -> dict:
    """``controller.controls(state)``, each value checked (ValueError naming it) and as
    float64."""
    out = controller.controls(state)
    if not isinstance(out, dict):
        raise ValueError(f"controller.controls: expected a dict of the driven controls, got {type(out).__name__}")
    checked = {}
    for name in controller.drives:
        if name not in out:
            raise ValueError(f"controller.controls: no {name!r} in its answer at t = {state.time:g} s")
        shape = {"wind": (3,), "rest_lengths": getattr(controls.springs, "shape", None),
                 "pin_targets": getattr(controls.pin_targets, "shape", (0, 0, 3))[1:]}[name]
        value = np.asarray(out[name], dtype=np.float64)
        if value.shape != shape or not np.all(np.isfinite(value)):
            raise ValueError(f"controller.controls: {name!r} at t = {state.time:g} s must be {shape} finite "
                             f"values, got shape {value.shape}")
        if name == "rest_lengths" and np.any(value < 0):
            raise ValueError(f"controller.controls: a rest length < 0 at t = {state.time:g} s")
        checked[name] = value
    return checked


def pullback(controller, state, cotangents) -> tuple:
    """``controller.vjp(state, cotangents)`` checked: (parameters' shares, dL/dx, dL/dv)."""
    out = controller.vjp(state, cotangents)
    if not (isinstance(out, tuple) and len(out) == 3 and isinstance(out[0], dict)):
        raise ValueError("controller.vjp: expected (parameters dict, positions (n, 3), velocities (n, 3))")
    params, dx, dv = out
    n = state.positions.shape[0]
    grads = {}
    for name, value in controller.parameters.items():
        share = np.asarray(params.get(name, 0.0), dtype=np.float64)
        if share.shape not in ((), np.shape(value)):
            raise ValueError(f"controller.vjp: parameter {name!r}'s share has shape {share.shape}, expected "
                             f"{np.shape(value)}")
        grads[name] = np.broadcast_to(share, np.shape(value))
    rows = []
    for label, value in (("positions", dx), ("velocities", dv)):
        value = np.zeros((n, 3)) if value is None else np.asarray(value, dtype=np.float64)
        if value.shape != (n, 3) or not np.all(np.isfinite(value)):
            raise ValueError(f"controller.vjp: {label} must be ({n}, 3) finite values, got shape {value.shape}")
        rows.append(value)
    return grads, rows[0], rows[1]
