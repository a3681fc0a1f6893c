"""The PyTorch bridge (``massspring.torch``, issue 63): a run as a ``torch.autograd.Function``.
Its value and gradients equal ``massspring.gradient``'s with the same network written as a
``SineNetwork`` (autograd's vector-Jacobian product of the module against the network's
own), its physics gradient agrees with central differences of its value, float32 modules
get float32 gradients, ``torch.optim`` trains through it, and bad arguments are refused by
name. Skipped where PyTorch is not installed (CI installs the JAX bridge's extra only:
docs/testing.md)."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")

import massspring as ms  # noqa: E402
from conftest import FULL  # noqa: E402
from massspring import torch as mstorch  # noqa: E402
from test_feedback import RUN, controlled, network, objective  # noqa: E402

WEIGHTS = np.random.default_rng(7).normal(size=(6, 16, 3))  # test_gradient.objective's, for 6 frames of 16 particles


def loss(positions, velocities):
    """``test_gradient.objective`` in torch: sum C . X + |V|^2 / 2."""
    return torch.sum(torch.as_tensor(WEIGHTS) * positions) + 0.5 * torch.sum(velocities ** 2)


class Network(torch.nn.Module):
    """A ``SineNetwork`` as a torch module, its weights copied, in ``dtype``."""

    def __init__(self, net, dtype=torch.float64):
        super().__init__()
        self.net = net
        for key, value in net.parameters.items():
            setattr(self, key, torch.nn.Parameter(torch.tensor(value, dtype=dtype)))

    def forward(self, x, v, t):
        net = self.net
        watched = torch.as_tensor(net.particles)
        clock = torch.sin(net.omega * t + 2 * np.pi * torch.arange(net.waves, dtype=x.dtype) / net.waves)
        xs = x[watched]
        u = torch.cat([clock, ((xs - xs.mean(dim=0)) * net.position_scale).reshape(-1),
                       (v[watched] * net.velocity_scale).reshape(-1)])
        h = torch.tanh(self.w1 @ u + self.b1)
        a = torch.tanh(self.w2 @ h + self.b2)
        return {"rest_lengths": torch.as_tensor(net.rest, dtype=x.dtype) * (1 + torch.as_tensor(
            net.actuation, dtype=x.dtype) * a)}


def test_the_bridge_gives_massspring_gradients_value_and_gradients():
    module = Network(network())
    stiffness = torch.tensor(controlled().stiffness, requires_grad=True)
    f = mstorch.simulation(controlled(), loss, policy=module, **RUN)
    value = f({"stiffness": stiffness})
    value.backward()
    names = [f"controller.{k}" for k in network().parameters] + ["stiffness"]
    expected_value, expected = ms.gradient(controlled(), objective, names, controller=network(), **RUN)
    assert float(value) == pytest.approx(expected_value, rel=1e-14)
    for key in network().parameters:
        grad = getattr(module, key).grad
        assert grad.dtype == torch.float64
        want = expected[f"controller.{key}"]
        assert np.allclose(grad.numpy(), want, rtol=1e-12, atol=1e-14 * np.abs(want).max()), key
    assert np.allclose(stiffness.grad.numpy(), expected["stiffness"], rtol=1e-12, atol=1e-16)


@FULL
def test_a_physics_gradient_agrees_with_central_differences_of_the_bridges_value():
    """Without a policy: d/d(damping) along a random direction, to 1e-6."""
    model = controlled().replaced(controls=None)
    f = mstorch.simulation(model, loss, **RUN)
    damping = torch.tensor(model.damping, requires_grad=True)
    f({"damping": damping}).backward()
    direction = torch.as_tensor(np.random.default_rng(3).normal(size=model.damping.shape))
    e = 1e-6
    with torch.no_grad():
        numeric = (float(f({"damping": damping + e * direction})) - float(f({"damping": damping - e * direction}))) / (2 * e)
    assert abs(float(torch.sum(damping.grad * direction)) - numeric) <= 1e-6 * abs(numeric)


@FULL
def test_a_float32_module_gets_float32_gradients_and_torch_optim_trains_it():
    """A float32 module (the run in float64): float32 gradients; five steps of
    ``torch.optim.SGD`` on the normalised gradient lower the loss each time."""
    module = Network(network(), dtype=torch.float32)
    f = mstorch.simulation(controlled(), loss, policy=module, **RUN)
    optimizer = torch.optim.SGD(module.parameters(), lr=0.2)
    values = []
    for _ in range(5):
        optimizer.zero_grad()
        value = f()
        value.backward()
        grads = [p.grad for p in module.parameters()]
        assert all(g.dtype == torch.float32 for g in grads)
        norm = torch.sqrt(sum(torch.sum(g ** 2) for g in grads))
        for g in grads:
            g /= norm
        optimizer.step()
        values.append(float(value))
    assert all(b < a for a, b in zip(values, values[1:])), values


def test_bad_arguments_are_refused_by_name():
    model = controlled()
    for kwargs, message in ((dict(model=object(), loss=loss), "model: expected a massspring.Model"),
                            (dict(model=model, loss=3), "loss: expected a torch function"),
                            (dict(model=model, loss=loss, policy=loss), "policy: expected a torch.nn.Module"),
                            (dict(model=model.replaced(controls=None), loss=loss, policy=Network(network())),
                             "policy: the model has no controls"),
                            (dict(model=model, loss=loss, wrt="stiffness"), "wrt: the bridge sets it")):
        with pytest.raises(ValueError, match=message):
            mstorch.simulation(**kwargs, **RUN)
    f = mstorch.simulation(model, loss, **RUN)
    with pytest.raises(ValueError, match="physics: unknown parameter 'stifness'"):
        f({"stifness": torch.ones(3)})
    with pytest.raises(ValueError, match="physics: 'stiffness' must be a torch tensor"):
        f({"stiffness": np.ones(3)})
    with pytest.raises(ValueError, match="policy, physics: nothing to differentiate"):
        f()
