"""Explicit Euler (seed Eq. 7-8, with the dt that Eq. 8 drops)."""

from __future__ import annotations

import dataclasses
import math

from massspring.support.defaults import FALLBACK_DT
from massspring.device import read_verdict
from massspring.kernels import divergence, euler

from .base import SwappingStates, Traits


class ExplicitEuler(SwappingStates):
    """x' = x + dt v, v' = v + dt f(x, v) / m: one fused kernel per step into a spare state.

    Serial: many steps per launch (``euler.euler_steps``); parallel: one
    ``euler.euler_step`` launch per step. First order; unstable for undamped
    oscillation at any dt (see ``analysis.stability``).
    """

    name = "explicit"
    description = "explicit Euler: x' = x + dt v, v' = v + dt f(x, v)/m"
    traits = Traits(order=1, grows_undamped=True, differentiable=True, stability_limited=True)
    symplectic = False

    @property
    def records_history(self) -> bool:
        """Whether ``advance`` can store each new state in a gradient's history (``history``):
        the serial kernels do, in the launch that makes them."""
        return self.serial

    def advance(self, steps):
        dev, cfg, dt = self.dev, self.cfg, self.dt
        if self.serial:
            a, b = self.states
            adj, slot = (dev, 0) if self.history is None else (self.history[0], self.steps + 1 - self.history[1])
            result = euler.euler_steps(dev, cfg, a, b, dt, self.time, steps, int(self.state is b), self.symplectic,
                                       adj, slot, self.history is not None)
            done, check = int(result[0]), read_verdict(result[1:])
            if done % 2:
                self.state, self.spare = self.spare, self.state
            self.count(done)
            return done, check
        done, check = 0, (divergence.OK, 0.0, 0.0)
        while done < steps and check[0] == divergence.OK:
            result = euler.euler_step(dev, cfg, self.state, self.spare, dt, self.time, self.symplectic)
            check = read_verdict(result)
            if check[0] == divergence.OK:
                self.state, self.spare = self.spare, self.state
                done += 1
                self.count(1)
        return done, check

    def adjoint(self, adj, slot, wants):
        """``euler.euler_adjoint`` of the step from the state kept at ``slot`` (no solve: None)."""
        wants, own = self._masses(wants)
        euler.euler_adjoint(self.dev, self.cfg, adj, self.state, self.dt, self.time + self.dt, slot,
                            self.symplectic, wants, own, self.serial)

    def __init__(self, dev, model, settings):
        super().__init__(dev, model, settings)
        self.moving_colliders = any(c.moving for c in model.colliders)

    def adjoint_steps(self, adj, slot, count, wants):
        """With serial loops and no moving collider (whose places depend on the time): the
        steps in one launch (``euler.euler_adjoints``)."""
        if not self.serial or self.moving_colliders:
            return False
        wants, own = self._masses(wants)
        euler.euler_adjoints(self.dev, self.cfg, adj, self.state, self.dt, slot, count, self.symplectic,
                             wants, own)
        return True

    def _masses(self, wants):
        """(``wants`` for the kernel, whether it takes the masses' gradient from the kept
        states: in f64 without colliders, ``euler.adjoint_step``)."""
        own = wants.masses and not self.cfg.has_colliders and self.settings.precision == "f64"
        return (dataclasses.replace(wants, masses=False) if own else wants), own

    @staticmethod
    def stability_limit(prediction):
        """The largest dt at which the stiffest mode does not grow (or, if larger, at which
        its energy doubles within a second)."""
        return max(prediction.explicit_stable_dt, prediction.explicit_doubling_dt)

    @classmethod
    def suggest_dt(cls, prediction):
        """Half ``stability_limit``."""
        limit = cls.stability_limit(prediction)
        return 0.5 * limit if math.isfinite(limit) else FALLBACK_DT
