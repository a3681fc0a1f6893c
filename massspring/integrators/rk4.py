"""Classical fourth-order Runge-Kutta (seed Eq. 4 as a first-order system)."""

from __future__ import annotations

import math

from massspring.support.defaults import FALLBACK_DT
from massspring.device import read_verdict
from massspring.kernels import divergence, rk4

from .base import SwappingStates, Traits

RK4_IMAGINARY_LIMIT = 2.0 * math.sqrt(2.0)  # |dt omega| where RK4's stability region meets the imaginary axis


def rk4_amplification(z: complex) -> float:
    """|R(z)|, R(z) = 1 + z + z^2/2 + z^3/6 + z^4/24: RK4's growth per step of y' = lambda y, z = lambda dt."""
    return abs(1 + z + z * z / 2 + z ** 3 / 6 + z ** 4 / 24)


def rk4_stable_dt(omega: float, rate: float) -> float:
    """The largest dt (s) at which both roots lambda of lambda^2 + rate lambda + omega^2 = 0
    (the damped mode x'' + rate x' + omega^2 x = 0) stay in RK4's stability region:
    overdamped modes (rate > 2 omega) are limited by their fast real root, about -rate,
    not by omega. Found by bisection along each root's ray (inf if both roots are 0)."""
    disc = complex(rate * rate - 4 * omega * omega)
    roots = [(-rate + sign * disc ** 0.5) / 2 for sign in (1, -1)]
    limits = []
    for root in roots:
        if abs(root) == 0:
            continue
        low, high = 0.0, 3.0 / abs(root)  # RK4's region lies within |z| < 3
        for _ in range(60):
            mid = 0.5 * (low + high)
            low, high = (mid, high) if rk4_amplification(root * mid) <= 1 + 1e-12 else (low, mid)
        limits.append(low)
    return min(limits) if limits else math.inf


class RK4(SwappingStates):
    """Four force evaluations per step (``kernels/rk4.py``); fourth order. The study's
    reference solutions are RK4 runs in f64. With colliders it gets the explicit
    integrators' contact response after each step, which is first order in dt."""

    name = "rk4"
    description = "classical Runge-Kutta, 4th order (4 force evaluations per step)"
    # keyframed_pins: its stages move a pin with the velocity in its state
    traits = Traits(order=4, differentiable=True, keyframed_pins=False, error_constant=1 / 120, stability_limited=True)

    def __init__(self, dev, model, settings):
        super().__init__(dev, model, settings)
        self.stage = dev.states["stage"]

    @classmethod
    def declare(cls, layout, model, settings):
        super().declare(layout, model, settings)
        layout.state("stage", layout.real)
        layout.vectors("sx", layout.real)
        layout.vectors("sv", layout.real)

    @classmethod
    def declare_adjoint(cls, layout, model, stride, rows):
        """The stages y2..y4 of the step run backwards (3 slots of ``stride`` rows) and the
        backward pass's per-stage vectors (``rk4.rk4_adjoint``)."""
        for name in ("xs", "vs"):
            layout.vectors(name, layout.real, 3 * stride)
        for name in ("kx", "yx", "yv", "ax", "av"):
            layout.vectors(name, layout.real)

    def adjoint(self, adj, slot, wants):
        """``rk4.rk4_adjoint`` of the step from the state kept at ``slot`` (no solve: None)."""
        rk4.rk4_adjoint(self.dev, self.cfg, adj, self.state, self.stage, self.dt,
                        self.time + self.dt, slot, wants, self.serial)

    def advance(self, steps):
        dev, cfg, dt = self.dev, self.cfg, self.dt
        if self.serial:
            a, b = self.states
            result = rk4.rk4_steps(dev, cfg, a, b, self.stage, dt, self.time, steps, int(self.state is b))
            done, check = int(result[0]), read_verdict(result[1:])
            if done % 2:
                self.state, self.spare = self.spare, self.state
            self.count(done)
            return done, check
        done, check = 0, (divergence.OK, 0.0, 0.0)
        while done < steps and check[0] == divergence.OK:
            result = rk4.rk4_step(dev, cfg, self.state, self.spare, self.stage, dt, self.time)
            check = read_verdict(result)
            if check[0] == divergence.OK:
                self.state, self.spare = self.spare, self.state
                done += 1
                self.count(1)
        return done, check

    @staticmethod
    def suggest_dt(prediction):
        """Half the dt at which the stiffest mode, with its damping, leaves RK4's stability
        region (``rk4_stable_dt``); 1e-2 s where nothing limits it."""
        limit = rk4_stable_dt(prediction.omega_max, prediction.damping_rate)
        return 0.5 * limit if math.isfinite(limit) else FALLBACK_DT
