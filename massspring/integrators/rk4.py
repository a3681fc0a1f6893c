"""Classical fourth-order Runge-Kutta (seed Eq. 4 as a first-order system)."""

from __future__ import annotations

import math

from massspring.kernels import divergence, rk4

from .base import Integrator

RK4_IMAGINARY_LIMIT = 2.0 * math.sqrt(2.0)  # |dt omega| where RK4's stability region meets the imaginary axis


class RK4(Integrator):
    """Four force evaluations per step (``kernels/rk4.py``); fourth order. The study's
    reference solutions are RK4 runs in f64. With colliders it gets the explicit
    integrators' contact response after each step, which is first order in dt."""

    name = "rk4"
    order = 4
    description = "classical Runge-Kutta, 4th order (4 force evaluations per step)"

    def __init__(self, dev, model, settings):
        super().__init__(dev, model, settings)
        self.spare = dev.states["spare"]
        self.stage = dev.states["stage"]

    @classmethod
    def declare(cls, layout, model, settings):
        layout.state("spare", layout.real)
        layout.state("stage", layout.real)
        layout.vectors("sx", layout.real)
        layout.vectors("sv", layout.real)

    def advance(self, steps):
        dev, cfg, dt = self.dev, self.cfg, self.settings.dt
        if self.serial:
            result = rk4.rk4_steps(dev, cfg, self.state, self.spare, self.stage, dt, self.time, steps)
            done, code, kinetic = int(result[0]), int(result[1]), float(result[2])
            if done % 2:
                self.state, self.spare = self.spare, self.state
            self.steps += done
            return done, code, kinetic
        done, code, kinetic = 0, divergence.OK, 0.0
        while done < steps and code == divergence.OK:
            result = rk4.rk4_step(dev, cfg, self.state, self.spare, self.stage, dt, self.time)
            code, kinetic = int(result[0]), float(result[1])
            if code == divergence.OK:
                self.state, self.spare = self.spare, self.state
                done += 1
                self.steps += 1
        return done, code, kinetic

    @staticmethod
    def suggest_dt(prediction):
        """Half the dt at which the undamped stiffest mode leaves RK4's stability region."""
        omega = prediction.omega_max
        return 0.5 * RK4_IMAGINARY_LIMIT / omega if omega > 0 else 1e-2
