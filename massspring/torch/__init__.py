"""PyTorch bridge (the optional extra ``[torch]``): a run of massspring as a differentiable
PyTorch function, so that a ``torch.nn.Module`` controller and ``torch.optim`` train
through the simulator.

    from massspring import torch as mstorch
    f = mstorch.simulation(model, loss, policy=module, steps=200, dt=1e-3, integrator="symplectic")
    value = f({"stiffness": k})       # a 0-d tensor
    value.backward()                  # fills module.parameters()' and k's .grad

``f(physics=None)`` runs ``massspring.gradient`` once (forward, then the discrete adjoint
backward) inside a ``torch.autograd.Function`` and hands its gradients to autograd's
backward pass: no trajectory is held by torch (the run's own checkpointing bounds its
memory). ``physics`` is a dict of ``massspring.gradient`` parameter names ("stiffness",
"rest_lengths", "positions", "controls.wind", ...) to tensors that replace the model's.

``loss(positions, velocities)`` is a torch function of the frames (F, n, 3) m and m/s
(float64 tensors; frame 0 the initial state, then every ``every``-th step) returning a
scalar. ``policy`` is a ``torch.nn.Module`` called as ``policy(positions, velocities,
time)`` at each interval's start (the state (n, 3) as tensors of its parameters' dtype,
time a float, s), returning a dict with, for each control the model's ``Controls`` hold
among "rest_lengths" ((c,) m), "wind" ((3,) m/s) and "pin_targets" ((k, 3) m), that interval's values: a feedback
controller (``massspring.Controller``) differentiated by ``torch.autograd.grad``.
Gradients come back in each tensor's dtype (float32 or float64); the run is float64.
"""

from __future__ import annotations

import numpy as np

try:
    import torch
except ImportError as exc:  # pragma: no cover - the message is the point
    raise ImportError("massspring.torch needs PyTorch: pip install 'massspring-taichi[torch]'") from exc

from massspring.gradients import PARAMETERS, check_bridge, gradient, with_parameters
from massspring.model.feedback import DRIVEN, Controller


class ModuleController(Controller):
    """A ``torch.nn.Module`` policy as a ``massspring.Controller`` of the controls
    ``controls`` holds (``DRIVEN``): its parameters those of ``module.parameters()`` that
    require grad, as float64 arrays "0", "1", ... in that order, read when made."""

    def __init__(self, module, controls):
        self.interval = controls.interval
        self.drives = tuple(name for name in DRIVEN if getattr(controls, name) is not None)
        self.springs = controls.springs
        self.module = module
        self.tensors = [p for p in module.parameters() if p.requires_grad]
        self.parameters = {str(i): p.detach().cpu().double().numpy().copy() for i, p in enumerate(self.tensors)}
        self.dtype = self.tensors[0].dtype if self.tensors else torch.float64

    def _call(self, state, grad):
        x = torch.tensor(state.positions, dtype=self.dtype, requires_grad=grad)
        v = torch.tensor(state.velocities, dtype=self.dtype, requires_grad=grad)
        out = self.module(x, v, float(state.time))
        if not isinstance(out, dict):
            raise ValueError(f"policy: expected a dict of the driven controls, got {type(out).__name__}")
        return x, v, out

    def controls(self, state):
        with torch.no_grad():
            _, _, out = self._call(state, False)
        return {name: out[name].detach().double().cpu().numpy() for name in self.drives if name in out}

    def vjp(self, state, cotangents):
        with torch.enable_grad():
            x, v, out = self._call(state, True)
            outputs = [out[name] for name in self.drives]
            weights = [torch.as_tensor(cotangents[name], dtype=o.dtype) for name, o in zip(self.drives, outputs)]
            grads = torch.autograd.grad(outputs, [*self.tensors, x, v], weights, allow_unused=True)
        as_numpy = [np.zeros(np.shape(t)) if g is None else g.detach().double().cpu().numpy()
                    for g, t in zip(grads, [*self.tensors, x, v])]
        params = {str(i): g for i, g in enumerate(as_numpy[:-2])}
        return params, as_numpy[-2], as_numpy[-1]


class _Run(torch.autograd.Function):
    """value = the run's loss; its inputs the policy's parameters then the physics tensors."""

    @staticmethod
    def forward(ctx, evaluate, count, names, *tensors):
        value, grads = evaluate(tensors[count:])
        ctx.grads = grads
        return torch.tensor(value, dtype=torch.float64)

    @staticmethod
    def backward(ctx, g):
        return (None, None, None, *[None if grad is None else g.to(grad.dtype) * grad for grad in ctx.grads])


def simulation(model, loss, *, policy=None, **run):
    """``f(physics=None) -> loss`` (a 0-d float64 tensor), differentiable by autograd in the
    policy's parameters and the physics tensors (see the module). ``run``:
    ``massspring.gradient``'s keywords (``steps``, ``every``, ``integrator``, ``dt``,
    ``checkpoint``, ``dts``, ``tol`` and ``times``, solver options). Bad arguments raise
    ValueError naming them, before any step."""
    if policy is not None and not isinstance(policy, torch.nn.Module):
        raise ValueError(f"policy: expected a torch.nn.Module, got {type(policy).__name__}")
    check_bridge(model, policy, run)
    if not callable(loss):
        raise ValueError(f"loss: expected a torch function of (positions, velocities), got {type(loss).__name__}")

    def objective(frames):
        x = torch.tensor(frames.positions, dtype=torch.float64, requires_grad=True)
        v = torch.tensor(frames.velocities, dtype=torch.float64, requires_grad=True)
        with torch.enable_grad():
            value = loss(x, v)
            dx, dv = torch.autograd.grad(value, [x, v], allow_unused=True)
        zero = np.zeros(frames.positions.shape)
        return float(value), {"positions": zero if dx is None else dx.detach().numpy(),
                              "velocities": zero if dv is None else dv.detach().numpy()}

    def f(physics=None):
        physics = {} if physics is None else dict(physics)
        for name, value in physics.items():
            if name not in PARAMETERS:
                raise ValueError(f"physics: unknown parameter {name!r}; expected some of {', '.join(PARAMETERS)}")
            if not isinstance(value, torch.Tensor):
                raise ValueError(f"physics: {name!r} must be a torch tensor, got {type(value).__name__}")
        controller = None if policy is None else ModuleController(policy, model.controls)
        names = list(physics)
        tensors = [] if controller is None else controller.tensors
        wrt = names + ([] if controller is None else [f"controller.{i}" for i in range(len(tensors))])
        if not wrt:
            raise ValueError("policy, physics: nothing to differentiate (give a policy with parameters or physics)")

        def evaluate(values):
            arrays = {name: value.detach().double().cpu().numpy() for name, value in zip(names, values)}
            value, grads = gradient(with_parameters(model, arrays), objective, wrt, controller=controller, **run)
            out = [torch.as_tensor(grads[f"controller.{i}"]).to(t.dtype) for i, t in enumerate(tensors)]
            out += [torch.as_tensor(np.asarray(grads[name])).to(t.dtype) for name, t in zip(names, values)]
            return value, out

        return _Run.apply(evaluate, len(tensors), tuple(names), *tensors, *physics.values())

    return f
