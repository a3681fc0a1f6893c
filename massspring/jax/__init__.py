"""JAX bridge (the optional extra ``[jax]``): a run of massspring as a differentiable JAX
function, so that ``jax.grad`` and any JAX optimiser (optax, ...) train through the simulator.

    from massspring import jax as msjax
    f = msjax.simulation(model, loss, policy=policy, steps=200, dt=1e-3, integrator="symplectic")
    value, grads = jax.value_and_grad(f)(params, {"stiffness": k})

``f(params, physics)`` runs ``massspring.gradient`` once: forward, then the discrete
adjoint backward, and keeps the gradient for ``jax.grad``'s backward pass
(``jax.custom_vjp``), so no trajectory is held by JAX (the run's own checkpointing bounds
its memory). ``params`` is a pytree of the ``policy``'s parameters, ``physics`` a dict of
``massspring.gradient`` parameter names ("stiffness", "rest_lengths", "positions",
"controls.wind", ...) to arrays that replace the model's. The function is not
``jax.jit``-able (it runs Taichi kernels); call it from Python, outside ``jit``.

``loss(positions, velocities)`` is a JAX function of the frames (F, n, 3) m and m/s (frame
0 the initial state, then every ``every``-th step) returning a scalar; ``policy(params,
positions, velocities, time)`` a JAX function returning, for each control the model's
``Controls`` hold among "rest_lengths" ((c,) m), "wind" ((3,) m/s) and "pin_targets" ((k, 3) m), that interval's
values from the state (n, 3) at its start, time s: a feedback controller
(``massspring.Controller``), differentiated by ``jax.vjp``. Both run under ``jax.jit``, once
compiled per shape. Arrays reach massspring as float64; gradients come back in each
input's dtype (with JAX's default float32, enable ``jax_enable_x64`` for f64 throughout).
"""

from __future__ import annotations

import numpy as np

try:
    import jax
    import jax.numpy as jnp
except ImportError as exc:  # pragma: no cover - the message is the point
    raise ImportError("massspring.jax needs JAX: pip install 'massspring-taichi[jax]'") from exc

from massspring.gradients import PARAMETERS, check_bridge, gradient, with_parameters
from massspring.model.feedback import DRIVEN, Controller


class CompiledPolicy:
    """A JAX ``policy(params, positions, velocities, time)`` setting ``drives``, under
    ``jax.jit`` once for a ``simulation`` (compiled once per shape of its arguments, not
    again for each call of the bridge's function): ``outputs`` and its ``pullback``."""

    def __init__(self, policy, drives):
        self.drives = drives

        def outputs(params, x, v, t):
            out = policy(params, x, v, t)
            return {name: jnp.asarray(out[name], dtype=jnp.result_type(float)) for name in drives}

        self.outputs = jax.jit(outputs)
        self.pullback = jax.jit(lambda params, x, v, t, cot: jax.vjp(
            lambda p, a, b: outputs(p, a, b, t), params, x, v)[1](cot))


class PolicyController(Controller):
    """A ``CompiledPolicy`` with the parameters ``params`` (a pytree) as a
    ``massspring.Controller`` of the controls ``controls`` holds: its parameters the
    pytree's leaves as float64 arrays "0", "1", ... in ``jax.tree_util`` order."""

    def __init__(self, compiled, params, controls):
        self.interval = controls.interval
        self.drives = compiled.drives
        self.springs = controls.springs
        self.compiled = compiled
        leaves, self.tree = jax.tree_util.tree_flatten(params)
        self.parameters = {str(i): np.asarray(leaf, dtype=np.float64) for i, leaf in enumerate(leaves)}

    def _params(self):
        return jax.tree_util.tree_unflatten(self.tree, [self.parameters[str(i)] for i in range(len(self.parameters))])

    def controls(self, state):
        out = self.compiled.outputs(self._params(), state.positions, state.velocities, state.time)
        return {name: np.asarray(value, dtype=np.float64) for name, value in out.items()}

    def vjp(self, state, cotangents):
        params, dx, dv = self.compiled.pullback(self._params(), state.positions, state.velocities, state.time,
                                                {name: cotangents[name] for name in self.drives})
        leaves = jax.tree_util.tree_leaves(params)
        return ({str(i): np.asarray(g, dtype=np.float64) for i, g in enumerate(leaves)},
                np.asarray(dx, dtype=np.float64), np.asarray(dv, dtype=np.float64))


def simulation(model, loss, *, policy=None, **run):
    """``f(params=None, physics=None) -> loss value``, differentiable by ``jax.grad`` in
    both (see the module). ``run``: ``massspring.gradient``'s keywords (``steps``,
    ``every``, ``integrator``, ``dt``, ``checkpoint``, ``dts``, ``tol`` and ``times``,
    solver options). Bad arguments raise ValueError naming them, before any step."""
    check_bridge(model, policy, run)
    if not callable(loss):
        raise ValueError(f"loss: expected a JAX function of (positions, velocities), got {type(loss).__name__}")
    if policy is not None and not callable(policy):
        raise ValueError(f"policy: expected a JAX function of (params, positions, velocities, time), got "
                         f"{type(policy).__name__}")
    partials = jax.jit(jax.value_and_grad(loss, argnums=(0, 1)))
    compiled = None if policy is None else CompiledPolicy(
        policy, tuple(name for name in DRIVEN if getattr(model.controls, name) is not None))

    def objective(frames):
        value, (dx, dv) = partials(frames.positions, frames.velocities)
        return float(value), {"positions": np.asarray(dx, dtype=np.float64),
                              "velocities": np.asarray(dv, dtype=np.float64)}

    def evaluate(params, physics):
        physics = {} if physics is None else dict(physics)
        for name in physics:
            if name not in PARAMETERS:
                raise ValueError(f"physics: unknown parameter {name!r}; expected some of {', '.join(PARAMETERS)}")
        controller = None
        if policy is not None:
            controller = PolicyController(compiled, params, model.controls)
        elif params is not None and jax.tree_util.tree_leaves(params):
            raise ValueError("params: without a policy there is nothing for them to set")
        run_model = with_parameters(model, {name: np.asarray(value, dtype=np.float64) for name, value in physics.items()})
        wrt = list(physics) + ([] if controller is None else [f"controller.{name}" for name in controller.parameters])
        if not wrt:
            raise ValueError("params, physics: nothing to differentiate (give a policy's params or physics)")
        value, grads = gradient(run_model, objective, wrt, controller=controller, **run)
        dparams = None
        if controller is not None:
            leaves = [grads[f"controller.{i}"] for i in range(len(controller.parameters))]
            dparams = jax.tree_util.tree_unflatten(controller.tree, leaves)
        return value, dparams, {name: grads[name] for name in physics}

    @jax.custom_vjp
    def f(params=None, physics=None):
        return jnp.asarray(evaluate(params, physics)[0])

    def forward(params, physics):
        value, dparams, dphysics = evaluate(params, physics)
        return jnp.asarray(value), (params, physics, dparams, dphysics)

    def backward(saved, g):
        params, physics, dparams, dphysics = saved
        like = lambda given, grad: jnp.asarray(g * grad, dtype=jnp.result_type(given))  # noqa: E731
        out_params = None if dparams is None else jax.tree_util.tree_map(like, params, dparams)
        out_physics = None if physics is None else {name: like(physics[name], dphysics[name]) for name in physics}
        return out_params, out_physics

    f.defvjp(forward, backward)
    return f

