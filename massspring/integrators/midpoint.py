"""Implicit midpoint solved by Newton's method (``kernels/newton.py``)."""

from __future__ import annotations

import dataclasses

from massspring.kernels import newton

from .newton import BackwardEuler


class Midpoint(BackwardEuler):
    """M (v' - v_n) = dt f((x_n + x')/2, (v_n + v')/2), x' = x_n + dt (v_n + v')/2.

    With w = (v_n + v')/2 the midpoint is x_n + (dt/2) w, so the step is backward Euler's
    equation (*) of ``kernels/newton.py`` with the base (x_n, v_n) and h = dt/2, solved for
    w, then v' = 2 w - v_n and x' = x_n + dt w (``newton.midpoint_finish``). Second order,
    symplectic, A-stable without numerical damping; it conserves the energy of a linear
    undamped system (a quadratic invariant) up to the solver's tolerance.

    The line search's merit function is backward Euler's incremental potential at h = dt/2,
    E(w) = 1/2 (w - v_n)^T M (w - v_n) + U(x_n + h w) + h Psi(w): its gradient is the
    midpoint residual divided by 2 (with Rayleigh damping at w, along the springs'
    directions at x_n + h v_n: ``kernels/newton.py``), so every solution of the
    step is a stationary point of it, and the Newton direction (from the definite,
    fixed operator) descends on it. A step with a particle in contact is a backward-Euler
    step (h = dt, v' = w), as BDF2's is: an impact makes the velocity jump, and
    extrapolating w across it would bounce the particle back (contact is first order in
    every integrator).

    Nonlinear springs break the energy argument: where stiff springs turn or buckle
    within a step, the midpoint's chord is shorter than the springs it stands for and
    the rule gains energy (Simo and Tarnow 1992), however tightly Newton solves it
    (measured: the chain at dt 1/60 diverges with newton_tol 1e-10 and no damping, as
    with the definiteness fix or without). So midpoint has a dt limit on such scenes,
    measured per shipped scene (their [dt] midpoint entries: docs/stability-and-study.md);
    ``suggest_dt`` gives a scene without one the explicit limit 2 / omega_max.
    """

    name = "midpoint"
    description = "implicit midpoint (second order, symplectic) solved by Newton's method with a line search"
    traits = dataclasses.replace(BackwardEuler.traits, order=2, error_constant=1 / 12)

    @staticmethod
    def suggest_dt(prediction):
        """2 / omega_max (symplectic Euler's limit on the stiffest mode), at most 1/60 s: a
        cautious default, each shipped scene's measured midpoint dt being larger (omega_max
        dt from 2.5 on the compressed cloth to 570 on the heavy chain: ``Midpoint``)."""
        omega = prediction.omega_max
        return min(1.0 / 60.0, 2.0 / omega) if omega > 0 else 1.0 / 60.0

    def ahead(self, h):
        return h

    def step_size(self, touching):
        return self.dt if touching else 0.5 * self.dt

    def solves_mean(self, touching):
        """Every step but one with a particle in contact (a backward-Euler step)."""
        return not touching

    def finish(self, h, touching):
        if not touching:
            newton.midpoint_finish(self.dev, self.cfg, h)
