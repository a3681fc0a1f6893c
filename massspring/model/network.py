"""``SineNetwork``: the small controller of DiffTaichi's mass-spring robots (Hu et al.,
ICLR 2020), a clock of sine waves and the robot's state through two tanh layers to
its muscles' rest lengths, in numpy with its exact vector-Jacobian product."""

from __future__ import annotations

import numpy as np

from massspring.model.controls import Controls
from massspring.model.feedback import ControlState, Controller
from massspring.support import validate
from massspring.support.validate import real_array


class SineNetwork(Controller):
    """A feedback controller of actuated rest lengths (``massspring.model.feedback``).

    At the start of each interval (time t, state x, v) it reads

        u = [sin(omega t + 2 pi j / waves), j < waves;
             (x_i - c) * position_scale, v_i * velocity_scale for the watched particles i]

    (c the watched particles' mean position) and sets the actuated springs' rest lengths

        l0 = rest * (1 + actuation * tanh(W2 tanh(W1 u + b1) + b2)).

    Parameters
    ----------
    interval : float > 0, s (the model's ``controls.interval``)
    springs : (c,) int, the actuated springs
    rest : (c,) float > 0, m: their rest lengths at zero activation
    actuation : float or (c,) float in [0, 1): the largest relative change of each
    particles : (p,) int, the particles the controller watches (p >= 1)
    hidden : int >= 1, the hidden layer's width (DiffTaichi: 32)
    waves : int >= 1, sine waves of the clock (DiffTaichi: 10)
    omega : float > 0, rad/s, the clock's angular frequency
    position_scale, velocity_scale : float >= 0, 1/m and s/m: the state's weights in u
    seed : int, for the initial weights (normal, scaled by sqrt(2 / (fan in + fan out)))

    ``parameters``: "w1" (hidden, waves + 6 p), "b1" (hidden,), "w2" (c, hidden), "b2"
    (c,); float64 arrays a training loop updates in place.
    """

    drives = ("rest_lengths",)

    def __init__(self, interval, springs, rest, actuation, particles, *, hidden=32, waves=10, omega=10.0,
                 position_scale=1.0, velocity_scale=0.1, seed=0):
        self.interval = validate.positive_float("interval", interval)
        springs = np.asarray(springs)
        if springs.ndim != 1 or not springs.size or springs.dtype.kind not in "iu":
            raise ValueError(f"springs: expected the actuated springs' indices (c,) int, got {springs!r}")
        self.springs = springs.astype(np.int64)
        c = springs.size
        self.rest = real_array("rest", rest).reshape(-1)
        if self.rest.shape != (c,) or np.any(self.rest <= 0):
            raise ValueError(f"rest: expected ({c},) rest lengths > 0 m, one per actuated spring")
        self.actuation = np.broadcast_to(real_array("actuation", actuation), (c,)).astype(np.float64)
        if np.any(self.actuation < 0) or np.any(self.actuation >= 1):
            raise ValueError("actuation: expected fractions in [0, 1) (the largest relative change of a rest length)")
        particles = np.asarray(particles)
        if particles.ndim != 1 or not particles.size or particles.dtype.kind not in "iu" or particles.min() < 0:
            raise ValueError(f"particles: expected the watched particles' indices (p,) int >= 0, got {particles!r}")
        self.particles = particles.astype(np.int64)
        self.waves = validate.count("waves", waves, low=1, high=1000)
        hidden = validate.count("hidden", hidden, low=1, high=100_000)
        self.omega = validate.positive_float("omega", omega)
        self.position_scale = validate.real_number("position_scale", position_scale, 0.0, ">=")
        self.velocity_scale = validate.real_number("velocity_scale", velocity_scale, 0.0, ">=")
        inputs = self.waves + 6 * self.particles.size
        rng = np.random.default_rng(seed)
        self.parameters = {
            "w1": rng.normal(size=(hidden, inputs)) * np.sqrt(2.0 / (inputs + hidden)),
            "b1": np.zeros(hidden),
            "w2": rng.normal(size=(c, hidden)) * np.sqrt(2.0 / (hidden + c)),
            "b2": np.zeros(c),
        }

    def top_speed(self) -> float:
        """The largest change of a rest length from one interval to the next, 2 actuation
        rest, by the interval (m/s)."""
        return float(np.max(2.0 * self.actuation * self.rest)) / self.interval

    def controls_for(self, intervals) -> Controls:
        """The model's ``Controls`` for a run of ``intervals`` intervals that this network
        drives (the values before it chooses them: the rest lengths at zero activation)."""
        intervals = validate.count("intervals", intervals, low=1, high=10**9)
        return Controls(self.interval, springs=self.springs, rest_lengths=np.tile(self.rest, (intervals, 1)))

    def _layers(self, state: ControlState):
        x = state.positions[self.particles]
        if x.shape[0] != self.particles.size:
            raise ValueError(f"particles: index {int(self.particles.max())} is outside the model's "
                             f"{state.positions.shape[0]} particles")
        clock = np.sin(self.omega * state.time + 2 * np.pi * np.arange(self.waves) / self.waves)
        u = np.concatenate([clock, ((x - x.mean(axis=0)) * self.position_scale).ravel(),
                            (state.velocities[self.particles] * self.velocity_scale).ravel()])
        p = self.parameters
        h = np.tanh(p["w1"] @ u + p["b1"])
        a = np.tanh(p["w2"] @ h + p["b2"])
        return u, h, a

    def controls(self, state: ControlState) -> dict:
        _, _, a = self._layers(state)
        return {"rest_lengths": self.rest * (1.0 + self.actuation * a)}

    def vjp(self, state: ControlState, cotangents: dict) -> tuple:
        u, h, a = self._layers(state)
        p = self.parameters
        g2 = cotangents["rest_lengths"] * self.rest * self.actuation * (1.0 - a * a)
        g1 = (p["w2"].T @ g2) * (1.0 - h * h)
        gu = p["w1"].T @ g1
        count = self.particles.size
        gx = gu[self.waves:self.waves + 3 * count].reshape(count, 3) * self.position_scale
        gv = gu[self.waves + 3 * count:].reshape(count, 3) * self.velocity_scale
        dx = np.zeros_like(state.positions)
        dv = np.zeros_like(state.velocities)
        np.add.at(dx, self.particles, gx - gx.mean(axis=0))  # through the centre too
        np.add.at(dv, self.particles, gv)
        grads = {"w1": np.outer(g1, u), "b1": g1, "w2": np.outer(g2, h), "b2": g2}
        return grads, dx, dv
