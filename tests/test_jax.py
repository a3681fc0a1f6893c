"""The JAX bridge (``massspring.jax``, issue 63): a run as a ``jax.custom_vjp`` function.
Its value and gradients equal ``massspring.gradient``'s with the same network written as
a ``SineNetwork`` (JAX's ``vjp`` of the policy against the network's own, and the bridge's
plumbing), its physics gradient agrees with central differences of its value, float32
inputs get float32 gradients, a few steps of gradient descent train through it, and bad
arguments are refused by name before any step."""

import numpy as np
import pytest

jax = pytest.importorskip("jax")
jnp = pytest.importorskip("jax.numpy")

import massspring as ms  # noqa: E402
from conftest import FULL  # noqa: E402
from massspring import jax as msjax  # noqa: E402
from test_feedback import RUN, controlled, network, objective  # noqa: E402

WEIGHTS = np.random.default_rng(7).normal(size=(6, 16, 3))  # test_gradient.objective's, for 6 frames of 16 particles


def loss(positions, velocities):
    """``test_gradient.objective`` in JAX: sum C . X + |V|^2 / 2."""
    return jnp.sum(WEIGHTS * positions) + 0.5 * jnp.sum(velocities ** 2)


def policy_of(net):
    """``net`` (a ``SineNetwork``) as a JAX policy of its parameters."""
    watched = net.particles

    def policy(p, x, v, t):
        clock = jnp.sin(net.omega * t + 2 * jnp.pi * jnp.arange(net.waves) / net.waves)
        xs = x[watched]
        u = jnp.concatenate([clock, ((xs - xs.mean(axis=0)) * net.position_scale).ravel(),
                             (v[watched] * net.velocity_scale).ravel()])
        h = jnp.tanh(p["w1"] @ u + p["b1"])
        return {"rest_lengths": net.rest * (1 + net.actuation * jnp.tanh(p["w2"] @ h + p["b2"]))}
    return policy


def test_the_bridge_gives_massspring_gradients_value_and_gradients():
    net = network()
    f = msjax.simulation(controlled(), loss, policy=policy_of(net), **RUN)
    with jax.enable_x64(True):
        params = {k: jnp.asarray(v) for k, v in net.parameters.items()}
        value, (dparams, dphysics) = jax.value_and_grad(f, argnums=(0, 1))(
            params, {"stiffness": jnp.asarray(controlled().stiffness)})
    names = [f"controller.{k}" for k in net.parameters] + ["stiffness"]
    expected_value, expected = ms.gradient(controlled(), objective, names, controller=network(), **RUN)
    assert float(value) == pytest.approx(expected_value, rel=1e-14)
    for key in net.parameters:
        assert dparams[key].dtype == jnp.float64
        assert np.allclose(dparams[key], expected[f"controller.{key}"], rtol=1e-12, atol=1e-14 * np.abs(
            expected[f"controller.{key}"]).max()), key
    assert np.allclose(dphysics["stiffness"], expected["stiffness"], rtol=1e-12, atol=1e-16)


@FULL
def test_a_physics_gradient_agrees_with_central_differences_of_the_bridges_value():
    """Without a policy: d/d(damping) along a random direction, to 1e-6."""
    model = controlled().replaced(controls=None)
    f = msjax.simulation(model, loss, **RUN)
    rng = np.random.default_rng(3)
    with jax.enable_x64(True):
        damping = jnp.asarray(model.damping)
        grad = jax.grad(f, argnums=1)(None, {"damping": damping})["damping"]
        direction = rng.normal(size=damping.shape)
        e = 1e-6
        numeric = (float(f(None, {"damping": damping + e * direction}))
                   - float(f(None, {"damping": damping - e * direction}))) / (2 * e)
    assert abs(float(np.sum(grad * direction)) - numeric) <= 1e-6 * abs(numeric)


@FULL
def test_float32_inputs_get_float32_gradients_and_training_lowers_the_loss():
    """JAX's default float32: the policy runs in float32 (the run in float64), the
    gradients come back as float32; five normalised gradient steps (DiffTaichi's update:
    0.2 / |g|) lower the loss each time."""
    net = network()
    f = msjax.simulation(controlled(), loss, policy=policy_of(net), **RUN)
    params = {k: jnp.asarray(v, dtype=jnp.float32) for k, v in net.parameters.items()}
    values = []
    for _ in range(5):
        value, grads = jax.value_and_grad(f)(params)
        assert all(g.dtype == jnp.float32 for g in jax.tree_util.tree_leaves(grads))
        norm = float(jnp.sqrt(sum(jnp.sum(g ** 2) for g in jax.tree_util.tree_leaves(grads))))
        params = jax.tree_util.tree_map(lambda p, g: p - 0.2 / norm * g, params, grads)
        values.append(float(value))
    assert all(b < a for a, b in zip(values, values[1:])), values


def test_bad_arguments_are_refused_by_name():
    model = controlled()
    for kwargs, message in ((dict(model=object(), loss=loss), "model: expected a massspring.Model"),
                            (dict(model=model, loss=3), "loss: expected a JAX function"),
                            (dict(model=model, loss=loss, policy=4), "policy: expected a JAX function"),
                            (dict(model=model.replaced(controls=None), loss=loss, policy=loss), "policy: the model has no controls"),
                            (dict(model=model, loss=loss, wrt="stiffness"), "wrt: the bridge sets it")):
        with pytest.raises(ValueError, match=message):
            msjax.simulation(**kwargs, **RUN)
    f = msjax.simulation(model, loss, **RUN)
    with pytest.raises(ValueError, match="physics: unknown parameter 'stifness'"):
        f(None, {"stifness": np.ones(3)})
    with pytest.raises(ValueError, match="params, physics: nothing to differentiate"):
        f(None, None)
